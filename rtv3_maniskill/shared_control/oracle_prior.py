"""A prior that knows the scene: the ceiling of what a learned prior can give the posterior.

One maneuver class per goal pre-grasp, each a Gaussian around the straight body twist to that
pre-grasp, ``e = se3_log(T_cur^-1 T_goal)`` (the twist that would reach it in one second, as the
simulated users compute it), norm-clipped to the controller's speed limits; translation and
rotation covariances are fixed (by default about the learned prior's median: 0.02 m/s and
0.1 rad/s standard deviations). Classes are equally likely. With every feasible goal of the scene
it is the ``oracle`` of the shared-control benchmark; with the true goal alone, ``oracle-goal``.
:class:`TargetShownPrior` is the other half of that split: the learned prior itself, shown only the
true target among the grasp candidates (``rtv3-goal``): what reading the goal from the user's
commands could at most give the learned prior.

It has the interface :class:`~rtv3_maniskill.shared_control.shared_controller.SharedController`
needs from a prior (``predict_step0_mixture``, ``reset``), so the fusion and the gate under test
are exactly the ones the learned prior gets.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.shared_control.twist_utils import as_poses, clamp_twist_speed, tcp_poses
from rtv3_maniskill.twist_mixture import TwistMixture


class OraclePrior:
    """Step-0 mixture with one class per goal, each pointing straight at its pre-grasp.

    Args:
        goals: ``(G, 4, 4)`` goal poses (world), e.g. pre-grasps; each is aimed at as the nearer
            of itself and its pi-about-z twin (parallel jaws). Settable later with :meth:`set_goals`.
        trans_std, rot_std: standard deviations (m/s, rad/s) of every class's Gaussians.
        max_linear_speed, max_angular_speed: norm clip of the class means (m/s, rad/s).
    """

    def __init__(self, goals: Any = None, trans_std: float = 0.02, rot_std: float = 0.1,
                 max_linear_speed: float | None = 0.3, max_angular_speed: float | None = 1.2) -> None:
        for name, value in (("trans_std", trans_std), ("rot_std", rot_std)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        self.trans_std, self.rot_std = float(trans_std), float(rot_std)
        self.max_linear_speed, self.max_angular_speed = max_linear_speed, max_angular_speed
        self.goals: torch.Tensor | None = None
        if goals is not None:
            self.set_goals(goals)

    def set_goals(self, goals: Any) -> None:
        """The goals of the coming episodes: ``(G, 4, 4)`` world poses, G >= 1."""
        self.goals = as_poses(goals, "goals")

    def reset(self) -> None:
        """Stateless between steps: nothing to forget (the goals stay)."""

    def straight_twists(self, observation: dict[str, Any]) -> torch.Tensor:
        """``(B, G, 6)`` float64 clipped straight body twists from each TCP to each goal (nearer twin)."""
        if self.goals is None:
            raise RuntimeError("OraclePrior has no goals: call set_goals(goals) first")
        tcp = tcp_poses(torch.as_tensor(observation[features.STATE]))  # (B, 4, 4)
        goals = self.goals[None].expand(tcp.shape[0], -1, -1, -1)
        twins = se3.rotate_about_z(goals, math.pi)
        rel = se3.relative_transform(tcp[:, None], goals)
        rel_twin = se3.relative_transform(tcp[:, None], twins)
        e, e_twin = se3.se3_log(rel), se3.se3_log(rel_twin)
        nearer = e_twin[..., 3:].norm(dim=-1) < e[..., 3:].norm(dim=-1)
        e = torch.where(nearer[..., None], e_twin, e)
        return clamp_twist_speed(e, self.max_linear_speed, self.max_angular_speed)

    def predict_step0_mixture(self, observation: dict[str, Any]) -> TwistMixture:
        """The mixture over the step-0 twist (body frame): ``K = G`` equally likely classes."""
        e = self.straight_twists(observation)
        b, g = e.shape[:2]
        eye = torch.eye(3, dtype=torch.float64)
        trans_cov = (self.trans_std**2 * eye).expand(b, g, 3, 3).clone()
        omega = e[..., 3:]
        rot_cov = self.rot_std**2 * eye

        def rotation_given_translation(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            shape = v.shape[:-1]
            return omega.expand(*shape, 3).to(v.dtype), rot_cov.expand(*shape, 3, 3).to(v.dtype)

        log_weights = torch.full((b, g), -math.log(g), dtype=torch.float64)
        return TwistMixture(log_weights, e[..., :3].clone(), trans_cov, rotation_given_translation)


class TargetShownPrior:
    """The learned prior shown only the trial's target among the observation's grasp candidates.

    Args:
        policy: a prior with ``predict_step0_mixture(observation)`` and ``reset()`` (the RT-V3 policy).
    The target is the index of the grasp candidate in ``observation.grasps`` (:meth:`set_target`).
    """

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.target: int | None = None

    def set_target(self, index: int) -> None:
        """The target grasp candidate's index of the coming episodes (>= 0)."""
        if int(index) < 0:
            raise ValueError(f"target index must be >= 0, got {index}")
        self.target = int(index)

    def reset(self) -> None:
        self.policy.reset()

    def predict_step0_mixture(self, observation: dict[str, Any]) -> TwistMixture:
        """The policy's step-0 mixture with ``observation.grasps_mask`` reduced to the target."""
        if self.target is None:
            raise RuntimeError("TargetShownPrior has no target: call set_target(index) first")
        mask = torch.as_tensor(observation[features.GRASPS_MASK])
        try:
            only = features.context_mask(mask, self.target, "target")
        except ValueError:
            raise ValueError(f"target {self.target} is not among the observation's {mask.shape[-1]} grasp candidates "
                             "(masked out or out of range)") from None
        return self.policy.predict_step0_mixture({**observation, features.GRASPS_MASK: only})
