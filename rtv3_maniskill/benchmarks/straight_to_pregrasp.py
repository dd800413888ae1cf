"""The NeoSS baseline's command for the planning benchmark (paper Table I's NeoSS row): a straight
body twist to the visible grasp's pre-grasp, clipped to the speed limits (m/s, rad/s); the NEO
collision damper in the controller (``pd_ee_twist_qp``) keeps it out of the scene."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.features import pregrasp_poses
from rtv3_maniskill.shared_control.oracle_prior import OraclePrior


class StraightToPregrasp:
    """The NeoSS baseline's command: the straight body twist ``se3_log(T_cur^-1 T_pre)`` to the nearer
    twin of the visible grasp's pre-grasp (one grasp: ``context="target"``), clipped to the speed
    limits; the damper in the controller keeps it out of the scene. Has the policy calls the
    benchmark makes (``reset``, ``select_action``) and the sizes it builds the env with."""

    def __init__(self, max_linear_speed: float = 0.3, max_angular_speed: float = 1.2) -> None:
        self._prior = OraclePrior(max_linear_speed=max_linear_speed, max_angular_speed=max_angular_speed)
        self.config = SimpleNamespace(num_points=features.DEFAULT_NUM_POINTS, max_grasps=features.DEFAULT_MAX_GRASPS)

    def reset(self) -> None:
        """Stateless."""

    def select_action(self, observation: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(1, 6)`` straight twist to the first visible grasp's pre-grasp."""
        grasps = features.unflatten(features.GRASPS, observation[features.GRASPS])[0].double()
        visible = torch.nonzero(observation[features.GRASPS_MASK][0] > 0.5).flatten()
        if len(visible) == 0:
            raise ValueError("the NeoSS planner needs a visible target grasp (context='target')")
        grasp = se3.pose_to_matrix(grasps[visible[0], :3], grasps[visible[0], 3:7])
        self._prior.set_goals(pregrasp_poses(grasp)[None])
        return self._prior.straight_twists(observation)[:, 0].float()
