"""A recursive belief over the scene's grasp candidates, read from the user's commands.

The learned prior's maneuver classes are not goals: class ``k`` at one step need not aim where
class ``k`` aimed at the step before, so evidence accumulated per class index (``belief_memory``)
follows a goal only as far as the classes keep their meaning. The grasp candidates of the
observation do keep theirs for a whole episode. This module scores each candidate as the user's
goal, step after step, and hands the prior only the candidates the user's commands have not
ruled out (the prior is trained on random subsets of the candidates, always with the target, so
any subset is an input it knows; with one candidate it is the goal-conditioned planner of the
planning benchmark).

Likelihood of a command ``u`` under candidate ``g`` (B batch, M candidate slots): the command
is a noisy observation of the straight body twist to ``g``'s pre-grasp,
``e_g = se3_log(T_tcp^-1 T_pregrasp_g)`` norm-clipped (the nearer of the pre-grasp and its
pi-about-z twin: parallel jaws), ``u ~ N(e_g, s C + S_u)`` on the command's observed axes only
(``C`` = diag of ``trans_std^2`` and ``rot_std^2``; ``s`` the fusion's ``prior_covariance_scale``),
which is :class:`~rtv3_maniskill.shared_control.oracle_prior.OraclePrior` with one class per
candidate, fused by :func:`~rtv3_maniskill.shared_control.posterior.prior_and_fused_mixtures`.
Evidence ``E_g <- memory E_g + log p(u | g)``, kept relative to the best candidate and floored.
"""

from __future__ import annotations

from typing import Any

import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.shared_control import posterior
from rtv3_maniskill.shared_control.oracle_prior import OraclePrior


class GoalBelief:
    """Evidence ``(B, M)`` (nats, 0 for the best candidate) per grasp-candidate slot since ``reset()``.

    Args:
        margin: candidates more than this many nats behind the best are withheld from the prior.
        memory: decay of the evidence per commanded step (1 = exact Bayes for a fixed goal).
        floor: the evidence never falls more than this many nats behind the best (a user who
            changes their mind can still be followed).
        trans_std, rot_std, covariance_scale: the likelihood's class covariance (m/s, rad/s;
            see the module docstring).
        max_linear_speed, max_angular_speed: norm clip of each straight twist (m/s, rad/s).
    """

    def __init__(self, margin: float, memory: float = 1.0, floor: float = 20.0, trans_std: float = 0.02,
                 rot_std: float = 0.1, covariance_scale: float = 1.0, max_linear_speed: float | None = 0.3,
                 max_angular_speed: float | None = 1.2) -> None:
        if not margin > 0 or not 0.0 <= memory <= 1.0 or not floor > 0 or not covariance_scale > 0:
            raise ValueError(f"GoalBelief needs margin > 0, memory in [0, 1], floor > 0 and covariance_scale > 0; "
                             f"got {margin}, {memory}, {floor}, {covariance_scale}")
        self.margin, self.memory, self.floor = float(margin), float(memory), float(floor)
        self.covariance_scale = float(covariance_scale)
        self._oracle = OraclePrior(trans_std=trans_std, rot_std=rot_std, max_linear_speed=max_linear_speed,
                                   max_angular_speed=max_angular_speed)
        self.evidence: torch.Tensor | None = None
        """``(B, M)`` float64, or None before the first command of an episode."""

    def reset(self) -> None:
        """A new episode: every candidate equally likely again."""
        self.evidence = None

    def update(self, observation: dict[str, Any], user: torch.Tensor, active: torch.Tensor,
               observed: torch.Tensor, user_trans_cov: torch.Tensor, user_rot_cov: torch.Tensor) -> None:
        """Add the evidence of this step's command ``user (B, 6)`` (body twist) where ``active (B,)``,
        on its ``observed (B, 6)`` axes, with the user covariances ``(B, 3, 3)`` S_u and G_u."""
        for key in (features.GRASPS, features.GRASPS_MASK):
            if key not in observation:
                raise ValueError(f"observation lacks {key!r}: the goal belief scores the grasp candidates")
        b = user.shape[0]
        grasps = torch.as_tensor(observation[features.GRASPS]).reshape(b, -1, features.GRASP_DIM)
        valid = torch.as_tensor(observation[features.GRASPS_MASK]).reshape(b, -1) > 0.5  # (B, M)
        m = valid.shape[1]
        if self.evidence is None or self.evidence.shape != (b, m):
            self.evidence = torch.zeros(b, m, dtype=torch.float64)
        state = torch.as_tensor(observation[features.STATE]).reshape(b, features.STATE_DIM)
        for i in torch.nonzero(active & valid.any(-1)).flatten().tolist():
            slots = torch.nonzero(valid[i]).flatten()
            rows = grasps[i, slots].double()
            quat_norm = rows[:, 3:7].norm(dim=-1)
            if not (torch.isfinite(rows[:, :7]).all() and ((quat_norm - 1.0).abs() < 1e-3).all()):
                raise ValueError(f"observation.grasps of batch element {i}: every valid candidate needs a finite "
                                 f"position and a unit quaternion wxyz (norms {quat_norm.tolist()})")
            self._oracle.set_goals(features.pregrasp_poses(se3.pose_to_matrix(rows[:, :3], rows[:, 3:7])))
            mixture = self._oracle.predict_step0_mixture({features.STATE: state[i:i + 1]})
            mixture = mixture.scaled(self.covariance_scale)
            prior, fused = posterior.prior_and_fused_mixtures(
                mixture, user[i:i + 1], user_trans_cov[i:i + 1], user_rot_cov[i:i + 1], observed=observed[i:i + 1])
            log_likelihood = (fused.log_weights - prior.log_weights)[0]  # up to a constant per step
            evidence = self.memory * self.evidence[i, slots] + log_likelihood
            self.evidence[i] = torch.full((m,), -self.floor, dtype=torch.float64)
            self.evidence[i, slots] = (evidence - evidence.max()).clamp_min(-self.floor)

    def kept(self, grasps_mask: torch.Tensor) -> torch.Tensor:
        """``(B, M)`` the grasp mask with the candidates more than ``margin`` behind the best removed."""
        mask = torch.as_tensor(grasps_mask)
        if self.evidence is None or self.evidence.numel() != mask.numel():
            return mask
        return mask * (self.evidence >= -self.margin).reshape(mask.shape).to(mask.dtype)

