"""RT-V3 shared controller: prior + user command -> executed body twist (paper, Sec. V).

Per step and batch element, one of three modes (:data:`MODES`, ``SharedControlDiagnostics.modes``):

* ``"shared"``: a user command arrived and is in distribution -> fuse it with the prior's step-0
  mixture on the command's observed axes (:func:`~rtv3_maniskill.shared_control.posterior.
  prior_and_fused_mixtures`; which zero axes are missing: :mod:`~rtv3_maniskill.shared_control.
  command_axes`) and execute the mode of the fused mixture
  (:func:`~rtv3_maniskill.shared_control.mode_search.mixture_mode`).
* ``"autonomous"`` (asynchronous mode): no user command (``None`` or all zeros) and the EE farther
  than ``autonomy_cutoff_distance`` from every scene point and from the table top -> execute the
  prior's most likely action (:mod:`~rtv3_maniskill.shared_control.autonomy`).
* ``"user_only"``: the user's own command is executed (zeros if none). Happens (a) with no command
  within ``autonomy_cutoff_distance`` of the scene (the user has control for the final approach),
  (b) in the out-of-distribution window: the command is farther than ``chi2.ppf(ood_alpha, d)``
  from every class (:mod:`~rtv3_maniskill.shared_control.ood_gate`) -> this step and the next
  ``ood_steps`` steps, class weights kept at the prior's; a new OOD command inside the window
  restarts it, (c) with an empty grasp set: the prior has nothing to condition on, so it is not
  called and the user drives alone.

The class weights carry the evidence of earlier commands (``belief_memory``;
:mod:`~rtv3_maniskill.shared_control.class_belief`), and the prior is shown only the grasp
candidates that a recursive belief over them keeps (``goal_belief_margin``;
:mod:`~rtv3_maniskill.shared_control.goal_belief`); the paper's prior sees them all. The user
covariances adapt to the user's commands (:mod:`~rtv3_maniskill.shared_control.user_covariance`).
Every output is clamped to ``max_linear_speed`` / ``max_angular_speed`` (norms).
"""

from __future__ import annotations

from typing import Any, Protocol

import torch

from rtv3_maniskill import features
from rtv3_maniskill.shared_control import ood_gate, posterior
from rtv3_maniskill.shared_control.autonomy import most_likely_twist, surface_distance
from rtv3_maniskill.shared_control.class_belief import EVIDENCE_FLOOR, ClassBelief
from rtv3_maniskill.shared_control.command_axes import observed_axes
from rtv3_maniskill.shared_control.config import SharedControlConfig
from rtv3_maniskill.shared_control.diagnostics import SharedControlDiagnostics
from rtv3_maniskill.shared_control.goal_belief import GoalBelief
from rtv3_maniskill.shared_control.mode_search import mixture_mode
from rtv3_maniskill.shared_control.twist_utils import clamp_twist_speed, step_inputs
from rtv3_maniskill.shared_control.user_covariance import UserCovarianceEstimator
from rtv3_maniskill.twist_mixture import TwistMixture

MODES = ("shared", "autonomous", "user_only")
"""The modes of a step, per batch element (``SharedControlDiagnostics.modes``)."""


class StepZeroPrior(Protocol):
    """What the controller needs from the learned prior (duck-typed)."""

    def predict_step0_mixture(self, observation: dict[str, torch.Tensor]) -> TwistMixture: ...

    def reset(self) -> None: ...


class SharedController:
    """RT-V3 shared control around a learned prior (see the module docstring for the modes).

    The same interface as every assistance method: ``reset()``, ``step(observation, user_twist)``
    and ``describe(index)``.

    Args:
        policy: has ``predict_step0_mixture(obs) -> TwistMixture`` (called once per step) and ``reset()``.
        config: :class:`SharedControlConfig`.
    """

    name = "rtv3"

    def __init__(self, policy: StepZeroPrior, config: SharedControlConfig | None = None) -> None:
        for name in ("predict_step0_mixture", "reset"):
            if not callable(getattr(policy, name, None)):
                raise TypeError(f"policy must have a callable {name}(); {type(policy).__name__} has none")
        self.policy = policy
        self.config = config or SharedControlConfig()
        self._batch_size: int | None = None
        self._ood_remaining = torch.zeros(0, dtype=torch.long)
        self._commanded_axes = torch.zeros(0, 6, dtype=torch.bool)
        """``(B, 6)`` axes the user has commanded since ``reset()`` (``uncommanded_axes``)."""
        self._user_cov: UserCovarianceEstimator | None = None
        self._class_belief = ClassBelief(self.config.belief_memory, EVIDENCE_FLOOR)
        self._goal_belief = self._make_goal_belief()
        self.last_diagnostics: SharedControlDiagnostics | None = None

    def _make_goal_belief(self) -> GoalBelief | None:
        c = self.config
        if c.goal_belief_margin is None:
            return None
        return GoalBelief(c.goal_belief_margin, memory=c.belief_memory, floor=EVIDENCE_FLOOR,
                          covariance_scale=c.prior_covariance_scale)

    def reset(self) -> None:
        """Start a new episode: reset the policy, the OOD window, the user covariance and the belief."""
        self.policy.reset()
        self._batch_size = None
        self._ood_remaining = torch.zeros(0, dtype=torch.long)
        self._commanded_axes = torch.zeros(0, 6, dtype=torch.bool)
        self._user_cov = None
        self._class_belief.reset()
        self._goal_belief = self._make_goal_belief()
        self.last_diagnostics = None

    def _init_batch(self, b: int) -> None:
        if self._batch_size is None:
            c = self.config
            self._batch_size = b
            self._ood_remaining = torch.zeros(b, dtype=torch.long)
            self._commanded_axes = torch.zeros(b, 6, dtype=torch.bool)
            self._user_cov = UserCovarianceEstimator(
                batch_size=b,
                init_trans_var=c.user_trans_var,
                init_rot_var=c.user_rot_var,
                window=c.user_cov_window,
                decay=c.user_cov_decay,
                floor=c.user_cov_floor,
            )
        elif b != self._batch_size:
            raise ValueError(f"batch size changed from {self._batch_size} to {b} without reset()")

    def step(self, observation: dict[str, torch.Tensor], user_twist: torch.Tensor | None) -> torch.Tensor:
        """One control step.

        Args:
            observation: feature dict (``rtv3_maniskill.features``), batched: needs
                ``observation.state (B, 27)``; ``observation.point_cloud`` (+ mask) for the autonomy
                cutoff and ``observation.grasps_mask`` for the empty-grasp fallback are optional.
            user_twist: ``(B, 6)`` body twist ``[v, w]`` of the user, or None (no command).
        Returns:
            ``(B, 6)`` float32 robot body twist, TCP frame.
        """
        # A step is ~1,500 small tensor operations: inference mode spares each its autograd and
        # version-counter bookkeeping. The twist handed out is an ordinary tensor again.
        with torch.inference_mode():
            action = self._step(observation, user_twist)
        return action.clone()

    def _step(self, observation: dict[str, torch.Tensor], user_twist: torch.Tensor | None) -> torch.Tensor:
        c = self.config
        _, user32 = step_inputs(observation, user_twist)
        user = user32.double()
        b = user.shape[0]
        self._init_batch(b)
        assert self._user_cov is not None
        active = user.norm(dim=-1) > c.input_threshold
        commanded = user.abs() > c.input_threshold  # (B, 6) the axes this command gives

        no_grasps = torch.zeros(b, dtype=torch.bool)
        grasps_mask = shown_grasps = candidates = None  # the observation's mask as given; (B, M) bool; (B,)
        if features.GRASPS_MASK in observation:
            grasps_mask = torch.as_tensor(observation[features.GRASPS_MASK])
            shown_grasps = grasps_mask.reshape(b, -1) > 0.5
            candidates = shown_grasps.sum(-1)
            no_grasps = candidates == 0

        dist = surface_distance(observation, c.table_height)
        in_window = self._ood_remaining > 0
        self._ood_remaining = (self._ood_remaining - 1).clamp_min(0)
        s_u, g_u = self._user_cov.trans_cov.clone(), self._user_cov.rot_cov.clone()

        action = user.clone()
        modes = ["user_only"] * b
        ood = in_window.clone()
        weights = prior_weights = torch.zeros(b, 0, dtype=torch.float64)
        shown: posterior.FactorizedTwistMixture | None = None

        # The command's axes that carry an observation (the others are missing: the prior fills them).
        observed = observed_axes(c.uncommanded_axes, commanded, self._commanded_axes,
                                 dist <= c.autonomy_cutoff_distance)

        if not bool(no_grasps.all()):
            prior_observation = observation
            if self._goal_belief is not None and grasps_mask is not None and features.GRASPS in observation:
                self._goal_belief.update(observation, user, active & ~no_grasps, observed, s_u, g_u)
                kept = self._goal_belief.kept(grasps_mask)
                prior_observation = {**observation, features.GRASPS_MASK: kept}
                shown_grasps = kept.reshape(b, -1) > 0.5
            mixture = self.policy.predict_step0_mixture(prior_observation)
            if mixture.log_weights.shape[0] != b:
                raise ValueError(f"policy returned a mixture of batch {mixture.log_weights.shape[0]}, expected {b}")
            mixture = self._class_belief.apply(mixture.scaled(c.prior_covariance_scale))
            fused = None
            fired = torch.zeros(b, dtype=torch.bool)
            if (active & ~no_grasps).any():
                prior, fused = posterior.prior_and_fused_mixtures(mixture, user, s_u, g_u, observed)
                fired = (active & ood_gate.is_out_of_distribution(fused, c.ood_alpha, c.ood_covariance)
                         & ~no_grasps)
            else:
                prior = posterior.prior_twist_mixture(mixture)
            self._ood_remaining = torch.where(fired, torch.full_like(self._ood_remaining, c.ood_steps),
                                              self._ood_remaining)
            ood = (in_window | fired) & ~no_grasps
            shared = active & ~ood & ~no_grasps
            autonomous = ~active & ~ood & ~no_grasps & (dist > c.autonomy_cutoff_distance)
            if shared.any():
                assert fused is not None
                mode = mixture_mode(fused, c.mode_search_starts, c.mode_search_iters, c.mode_search_tol)
                action = torch.where(shared[:, None], mode, action)
            if autonomous.any():
                action = torch.where(autonomous[:, None], most_likely_twist(prior), action)
            modes = ["shared" if s else "autonomous" if a else "user_only"
                     for s, a in zip(shared.tolist(), autonomous.tolist())]
            # Diagnostics: the fused mixture where it was executed, the prior's elsewhere.
            shown = prior
            if fused is not None and shared.any():
                shown = posterior.FactorizedTwistMixture(
                    *(torch.where(shared.view(b, *[1] * (f.ndim - 1)), f, p) for f, p in (
                        (fused.log_weights, prior.log_weights),
                        (fused.trans_mean, prior.trans_mean),
                        (fused.trans_cov, prior.trans_cov),
                        (fused.rot_mean, prior.rot_mean),
                        (fused.rot_cov, prior.rot_cov),
                    )),
                    prior_log_weights=prior.log_weights,
                )
            prior_weights = prior.weights
            weights = shown.weights
            self._class_belief.remember(shared, prior, fused)
        self._user_cov.update(user, active)
        self._commanded_axes = self._commanded_axes | commanded

        action = clamp_twist_speed(action, c.max_linear_speed, c.max_angular_speed)
        if not torch.isfinite(action).all():  # defensive: never send NaN to a robot
            raise FloatingPointError("shared controller produced a non-finite twist")
        self.last_diagnostics = SharedControlDiagnostics(
            modes=tuple(modes),
            class_weights=weights,
            prior_class_weights=prior_weights,
            ood=ood,
            surface_distance=dist,
            user_trans_cov=s_u,
            user_rot_cov=g_u,
            fallback=no_grasps,
            mixture=shown,
            shown_grasps=shown_grasps,
            grasp_candidates=candidates,
        )
        return action.float()

    def describe(self, index: int = 0) -> dict[str, Any]:
        """The last step of batch element ``index``: mode, class weights (posterior where shared,
        the prior's otherwise), the prior's weights, entropy bounds, OOD flag, surface distance and,
        with grasp candidates, the indices of those the prior was shown, their number in all and, once the
        user has commanded, ``grasp_belief (M,)``: the belief over the candidates (probabilities)."""
        d = self.last_diagnostics
        if d is None:
            return {"mode": ""}
        grasps = {}
        if d.shown_grasps is not None and d.grasp_candidates is not None:
            grasps = {"shown_grasps": torch.nonzero(d.shown_grasps[index]).flatten().numpy(),
                      "grasp_candidates": int(d.grasp_candidates[index])}
            evidence = None if self._goal_belief is None else self._goal_belief.evidence
            if evidence is not None and index < evidence.shape[0]:  # (M,) the belief over the candidates
                grasps["grasp_belief"] = torch.softmax(evidence[index], -1).numpy().copy()
        return {
            "mode": d.modes[index],
            "class_weights": d.class_weights[index].numpy().copy(),
            "prior_class_weights": d.prior_class_weights[index].numpy().copy(),
            "trans_entropy_lower": float(d.trans_entropy_lower[index]),
            "trans_entropy_upper": float(d.trans_entropy_upper[index]),
            "rot_entropy_lower": float(d.rot_entropy_lower[index]),
            "rot_entropy_upper": float(d.rot_entropy_upper[index]),
            "ood": bool(d.ood[index]),
            "surface_distance": float(d.surface_distance[index]),
            **grasps,
        }
