"""The planning oracle (``oracle-plan``): a prior that knows the true goal and the way around the clutter.

One maneuver class, a Gaussian (an :class:`~rtv3_maniskill.shared_control.oracle_prior.OraclePrior`'s,
5 mm/s translation standard deviation, chosen on validation scenes: the straight oracles' 20 mm/s lets
the noisy user's command pull the hand off the path) around the twist that follows the motion planner's
collision-free path
(:class:`~rtv3_maniskill.robot.planner.PandaPlanner`: RRT-Connect, then TOPP-RA at 20 Hz) from the
arm's current configuration to the goal's pre-grasp: the body twist that reaches the path's pose
``lookahead_steps`` samples past the nearest one in that many control steps. When the hand is more
than ``replan_distance`` from the path (the user or the fusion pulled it off), the path is planned
again from where the arm is, at most every ``min_replan_steps`` steps; where no path is found (no
collision-free IK at the pre-grasp, or the planner's time runs out) the class points straight at the
pre-grasp, as ``oracle-goal``'s does. Run through the same fusion and gate as RT-V3, it is the
ceiling of a prior that plans around the clutter, which the straight-line oracles are not on
cluttered scenes. The benchmark builds it by name (``oracle_plan`` of
:data:`~rtv3_maniskill.shared_control.methods.METHODS`, this class handed in as ``plan_prior``) and
tells it each trial's planner and target (:meth:`PlanOraclePrior.set_trial`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.benchmarks.goals import aimed_pregrasp
from rtv3_maniskill.shared_control.oracle_prior import OraclePrior
from rtv3_maniskill.twist_mixture import TwistMixture


class PlanOraclePrior:
    """Step-0 mixture of one class following the planner's path to the goal (see the module docstring).

    Args:
        trans_std, rot_std, max_linear_speed, max_angular_speed: as :class:`OraclePrior`.
        lookahead_steps: path samples (0.05 s each) ahead of the nearest one that the twist aims at.
        replan_distance: m between the TCP and the nearest path pose beyond which the path is planned again.
        min_replan_steps: control steps between two plans.
        plan_timeout: s per planner call.
    """

    def __init__(self, trans_std: float = 0.005, rot_std: float = 0.1, max_linear_speed: float | None = 0.3,
                 max_angular_speed: float | None = 1.2, lookahead_steps: int = 4, replan_distance: float = 0.02,
                 min_replan_steps: int = 10, plan_timeout: float = 1.0) -> None:
        if lookahead_steps < 1 or min_replan_steps < 1 or not replan_distance > 0 or not plan_timeout > 0:
            raise ValueError("lookahead_steps and min_replan_steps must be >= 1, replan_distance and plan_timeout > 0")
        self._oracle = OraclePrior(trans_std=trans_std, rot_std=rot_std, max_linear_speed=max_linear_speed,
                                   max_angular_speed=max_angular_speed)
        self.lookahead_steps, self.min_replan_steps = int(lookahead_steps), int(min_replan_steps)
        self.replan_distance, self.plan_timeout = float(replan_distance), float(plan_timeout)
        self.planner: Any = None
        self.goal: np.ndarray | None = None
        self.plans = 0
        self.reset()

    def set_goal(self, planner: Any, goal: Any) -> None:
        """The coming episodes' scene planner (a ``PandaPlanner`` of the loaded layout) and goal ``(4, 4)``
        (world; the pre-grasp of the grasp twin the user aims at)."""
        goal = np.asarray(goal, dtype=np.float64)
        if goal.shape != (4, 4) or not np.isfinite(goal).all():
            raise ValueError(f"goal must be a finite (4, 4) pose, got shape {goal.shape}")
        self.planner, self.goal = planner, goal

    def set_trial(self, trial: Any) -> None:
        """The coming episodes' :class:`~rtv3_maniskill.shared_control.methods.Trial`: its planner, and as
        the goal the pre-grasp of the target's twin a user aims at from the ready pose."""
        self.set_goal(trial.planner, aimed_pregrasp(trial.planner, trial.grasp_pose))

    def reset(self) -> None:
        """A new episode: plan again from its start."""
        self._path: np.ndarray | None = None  # (S, 4, 4) TCP poses along the plan
        self._index = 0
        self._since_plan = self.min_replan_steps

    def _plan(self, q: np.ndarray) -> None:
        self._since_plan, self._index = 0, 0
        self.plans += 1
        result = self.planner.plan_to_pose(q, self.goal, timeout=self.plan_timeout, seed=self.plans)
        if not result.success:
            self._path = None
            return
        self._path = np.stack([self.planner.forward_kinematics(qi) for qi in result.trajectory.q])

    def _aim(self, tcp: np.ndarray, q: np.ndarray) -> np.ndarray:
        """The pose the class's twist reaches in one second: the goal, or a point ahead on the path."""
        if self.planner is None or self.goal is None:
            raise RuntimeError("PlanOraclePrior has no goal: call set_goal(planner, goal) first")
        self._since_plan += 1
        if self._path is None and self._since_plan >= self.min_replan_steps:
            self._plan(q)
        if self._path is not None:
            window = self._path[self._index:self._index + 4 * self.lookahead_steps + 1, :3, 3]
            nearest = self._index + int(np.argmin(np.linalg.norm(window - tcp[:3, 3], axis=1)))
            off_path = np.linalg.norm(self._path[nearest, :3, 3] - tcp[:3, 3]) > self.replan_distance
            if off_path and self._since_plan >= self.min_replan_steps:
                self._plan(q)
                if self._path is None:
                    return self.goal
                nearest = 0
            self._index = nearest
            ahead = min(nearest + self.lookahead_steps, len(self._path) - 1)
            if ahead > nearest:  # a pose `steps` samples on, reached in `steps` control steps
                steps = ahead - nearest
                twist = se3.se3_log(se3.relative_transform(torch.from_numpy(tcp), torch.from_numpy(self._path[ahead])))
                return (torch.from_numpy(tcp) @ se3.se3_exp(twist / (steps * features.DT))).numpy()
        return self.goal

    def predict_step0_mixture(self, observation: dict[str, Any]) -> TwistMixture:
        """One class (body frame) around the twist along the path; batch size 1."""
        state = torch.as_tensor(observation[features.STATE]).reshape(-1, features.STATE_DIM).double()
        if state.shape[0] != 1:
            raise ValueError(f"PlanOraclePrior drives one env, got a batch of {state.shape[0]}")
        tcp = se3.pose_to_matrix(state[0, features.EE_POS], state[0, features.EE_QUAT]).numpy()
        self._oracle.set_goals(torch.from_numpy(self._aim(tcp, state[0, features.ARM_QPOS].numpy()))[None])
        return self._oracle.predict_step0_mixture(observation)


__all__ = ["PlanOraclePrior"]
