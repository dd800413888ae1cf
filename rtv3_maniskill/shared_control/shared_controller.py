"""RT-V3 shared controller: prior + user command -> executed body twist (paper, Sec. Posterior Decision Making).

Per step and batch element, one of three modes (``SharedControlDiagnostics.modes``):

* ``"shared"``: a user command arrived and is in distribution -> fuse it with the
  prior's step-0 mixture (:func:`posterior.prior_and_fused_mixtures`, which also gives the prior
  mixture, :func:`posterior.fuse_user_command` alone) and execute the mode of
  the fused mixture (:func:`mode_search.mixture_mode`). The zero axes of a command are, by
  default (``uncommanded_axes="missing_unused"``), axes the device does not give, not fused, so
  the prior fills them in (a mode-switching or single-axis user), as long as the user has never
  commanded that axis and the EE is farther than ``autonomy_cutoff_distance`` from the scene; a
  zero on an axis the user has commanded before, and near the scene a zero axis of a kind
  (translation or rotation) the user has commanded before, means "hold still".
* ``"autonomous"``: no user command (``None`` or all zeros), asynchronous mode on, and
  the EE is farther than ``autonomy_cutoff_distance`` from every scene point and from the table
  top (``table_height``; the cloud is cropped above it) -> execute
  the prior's most likely action (argmax class, then its Gaussians' means; :func:`most_likely_twist`).
* ``"user_only"``: the user's own command is executed (zeros if none). Happens (a) with
  no command within ``autonomy_cutoff_distance`` of the object surface (the user has
  control for the final approach), (b) in the out-of-distribution window: the command's
  observed axes are farther than ``chi2.ppf(ood_alpha, d)`` (squared Mahalanobis under the
  class covariances, ``d`` observed axes; :func:`ood_gate.is_out_of_distribution` for the
  variants in docs/PAPER_DETAILS.md) from every class -> this step and the next ``ood_steps`` steps, class
  weights kept at the prior's (no re-weighting with an OOD command); a new OOD command
  inside the window restarts it, (c) the documented fallback for an empty grasp set:
  with no candidate grasps the prior has nothing to condition on, so the policy is not
  called and the user drives alone.

In every mode that calls the prior, the prior is shown only the grasp candidates that a recursive
belief over them, built from the user's commands, keeps (``goal_belief_margin``;
:mod:`~rtv3_maniskill.shared_control.goal_belief`); the paper's prior sees them all.

Every output is clamped to ``max_linear_speed`` / ``max_angular_speed`` (norms).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Protocol

import torch

from rtv3_maniskill import features
from rtv3_maniskill.shared_control import mixture_entropy, ood_gate, posterior
from rtv3_maniskill.shared_control.goal_belief import GoalBelief
from rtv3_maniskill.shared_control.mode_search import mixture_mode
from rtv3_maniskill.shared_control.twist_utils import check_speed_limits, clamp_twist_speed, step_inputs
from rtv3_maniskill.shared_control.user_covariance import UserCovarianceEstimator
from rtv3_maniskill.twist_mixture import TwistMixture

MODES = ("shared", "autonomous", "user_only")
EVIDENCE_FLOOR = 20.0
"""Nats: the recursive belief never rules a class out by more than this (``belief_memory``)."""
UNCOMMANDED_AXES = ("missing", "zero", "missing_far", "missing_far_group", "missing_unused",
                    "missing_unused_group")


class StepZeroPrior(Protocol):
    """What the controller needs from the learned prior (duck-typed)."""

    def predict_step0_mixture(self, observation: dict[str, torch.Tensor]) -> TwistMixture: ...


    def reset(self) -> None: ...


@dataclass
class SharedControlConfig:
    """Settings of :class:`SharedController`. Units: m, m/s, rad/s."""

    max_linear_speed: float | None = 0.5
    """Norm limit on the executed translation velocity (m/s); None = no limit."""
    max_angular_speed: float | None = 1.5
    """Norm limit on the executed rotation velocity (rad/s); None = no limit."""
    asynchronous: bool = True
    """Execute the prior's most likely action while the user gives no command (paper)."""
    autonomy_cutoff_distance: float = 0.07
    """Asynchronous autonomy is off within this distance (m) of the nearest scene point.
    The paper gives no number; 7 cm sits just outside the 5 cm pre-grasp offset."""
    table_height: float | None = 0.0
    """World z (m) of the table top, part of the scene for ``autonomy_cutoff_distance`` (the point
    cloud is cropped above it); ``GraspClutter-v1``'s table top is at 0. None: the cloud alone."""
    input_threshold: float = 1e-6
    """A user twist with norm <= this counts as "no command"; an axis with ``|u_i|`` <= this
    counts as not commanded (see ``uncommanded_axes``)."""
    ood_alpha: float = 0.99
    """OOD gate: chi2 quantile on the squared Mahalanobis distance (the paper: 0.85)."""
    ood_steps: int = 3
    """Steps after an OOD command during which the user's command is executed."""
    ood_covariance: str = "predictive"
    """Covariance of the OOD test's Mahalanobis distance: ``"predictive"`` (``Sigma_k + S_u``: a
    command is judged with the user's own noise) or ``"class"`` (``Sigma_k``, docs/PAPER_DETAILS.md's
    "distance to the nearest class", the paper's reading); see :func:`ood_gate.is_out_of_distribution`."""
    ood_dofs: str = "twist"
    """What the OOD test looks at: ``"twist"`` (translation and rotation) or ``"translation"``
    (docs/PAPER_DETAILS.md); see :func:`ood_gate.is_out_of_distribution`."""
    uncommanded_axes: str = "missing_unused"
    """How a zero axis of a user command (``|u_i| <= input_threshold``) of a command that is not
    zero altogether is read: ``"missing"``, an axis the device does not give (a mode-switching
    or single-axis user), so neither the fusion nor the OOD test uses it and the prior fills it
    in; ``"zero"`` (the paper's and docs/PAPER_DETAILS.md's reading), an observation "hold still" on that axis;
    ``"missing_far"``, "hold still" within ``autonomy_cutoff_distance`` of the scene if the user has
    commanded that axis since ``reset()`` (it is on the device: there, filling it is autonomy near
    clutter), missing otherwise (farther away, or an axis the device never gave, e.g. a
    translation-only device's rotation); ``"missing_far_group"``, the same with the
    device's axes known by kind: once the user has commanded any translation (rotation) axis, every
    translation (rotation) axis is on the device, so near the scene the prior fills none of them
    (a one-axis-at-a-time user no longer has the prior turn or push the hand about the axes it has
    not reached yet); ``"missing_unused"`` (the default), that near the scene, and anywhere a zero on an axis the
    user has commanded since ``reset()`` means "hold still" (the user has left that axis: the prior no
    longer continues there the motion the user gave it), while axes never commanded stay the prior's
    far from the scene; ``"missing_unused_group"``, the prior fills only the kinds the user has never
    commanded since ``reset()``, anywhere: once the user has commanded any translation (rotation)
    axis, a zero translation (rotation) axis means "hold still" far from the scene too (the prior
    no longer continues, on the axis a one-axis-at-a-time user has just left, the motion the user
    gave it)."""
    user_trans_var: float = 0.03
    """Initial S_u diagonal ((m/s)^2)."""
    user_rot_var: float = 0.1
    """Initial G_u diagonal ((rad/s)^2)."""
    adapt_user_covariance: bool = True
    user_cov_window: int = 14
    user_cov_decay: float = 0.8
    user_cov_floor: float = 0.01
    reweight_rotation_at: str = "prior"
    """See :func:`posterior.fuse_user_command` ("prior" = paper, "fused" = docs/PAPER_DETAILS.md)."""
    belief_memory: float = 1.0
    """Recursive goal belief. 0 (the paper): every step's class weights are the prior's alone, the
    evidence of earlier commands is forgotten. In (0, 1]: the log-likelihood of the user's commands
    under each class is accumulated over the shared steps, decayed by this factor per step, and
    added to the prior's log-weights, so consistent commands build up a belief in one class (1 =
    exact Bayes for a goal that does not change)."""
    goal_belief_margin: float | None = 1.0
    """Goal-tracking prior input (:mod:`~rtv3_maniskill.shared_control.goal_belief`). None (the paper):
    the prior sees every grasp candidate at every step. A number of nats: the controller keeps a
    recursive belief over the candidates from the user's commands (each a noisy straight twist to
    its candidate's pre-grasp, on the command's observed axes; evidence decayed by ``belief_memory``)
    and hands the prior only the candidates within this many nats of the most likely one. 1 was
    chosen on validation goals (it lifts a translation-only user most: the prior then turns the
    hand towards the grasp the user drives to)."""
    prior_covariance_scale: float = 100.0
    """Factor on the prior's step-0 covariances (Sigma_z and Gamma_z) before the gate and the
    fusion. 1 (the paper) takes the prior as calibrated; a learned prior is calibrated on its
    training data (`rtv3 evaluate prediction` reports its step-0 coverage) but overconfident where
    its own closed loop leads it (on DAgger states its maximum-likelihood scale is ~20), and a larger
    factor gives the user's command more weight (Kalman gain ``K = s Sigma_z (s Sigma_z + S_u)^-1``).
    100 was chosen on validation goals."""
    mode_search_starts: int = 3
    mode_search_iters: int = 10
    """Most mean-shift iterations of the mode search (:func:`mode_search.mixture_mode`)."""
    mode_search_tol: float = 1e-6
    """Stop the mode search once no iterate moves by more than this (m/s, rad/s)."""

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> SharedControlConfig:
        """A named fusion (:data:`FUSION_PRESETS`), with ``overrides`` on top.

        ``"tuned"`` (the defaults) was chosen on validation scenes so that a prior that knows the
        scene helps every simulated user and the shipped prior loses to Direct for none;
        ``"paper"`` is the paper's reading: the gate under the
        class covariance at alpha 0.85, no memory of earlier commands, the prior's covariances as
        predicted (and a command's zero axes missing everywhere, as before ``"missing_far"``).
        """
        if name not in FUSION_PRESETS:
            raise ValueError(f"unknown fusion preset {name!r}; known: {', '.join(FUSION_PRESETS)}")
        return cls(**{**FUSION_PRESETS[name], **overrides})

    def __post_init__(self) -> None:
        check_speed_limits(self.max_linear_speed, self.max_angular_speed)
        if not (math.isfinite(self.autonomy_cutoff_distance) and self.autonomy_cutoff_distance >= 0):
            raise ValueError(f"autonomy_cutoff_distance must be >= 0, got {self.autonomy_cutoff_distance}")
        if self.table_height is not None and not math.isfinite(self.table_height):
            raise ValueError(f"table_height must be a finite height (m) or None, got {self.table_height}")
        if self.ood_steps < 0:
            raise ValueError(f"ood_steps must be >= 0, got {self.ood_steps}")
        if self.ood_covariance not in ood_gate.OOD_COVARIANCES:
            raise ValueError(f"ood_covariance must be one of {ood_gate.OOD_COVARIANCES}, got {self.ood_covariance!r}")
        if self.ood_dofs not in ood_gate.OOD_DOFS:
            raise ValueError(f"ood_dofs must be one of {ood_gate.OOD_DOFS}, got {self.ood_dofs!r}")
        if self.uncommanded_axes not in UNCOMMANDED_AXES:
            raise ValueError(f"uncommanded_axes must be one of {UNCOMMANDED_AXES}, got {self.uncommanded_axes!r}")
        if self.reweight_rotation_at not in ("prior", "fused"):
            raise ValueError(f"reweight_rotation_at must be 'prior' or 'fused', got {self.reweight_rotation_at!r}")
        if self.mode_search_starts < 1 or self.mode_search_iters < 0 or not self.mode_search_tol >= 0:
            raise ValueError("need mode_search_starts >= 1, mode_search_iters >= 0 and mode_search_tol >= 0, got "
                             f"{self.mode_search_starts}, {self.mode_search_iters}, {self.mode_search_tol}")
        ood_gate.ood_threshold(self.ood_alpha)  # validates alpha
        if not 0.0 <= self.belief_memory <= 1.0:
            raise ValueError(f"belief_memory must be in [0, 1], got {self.belief_memory}")
        if self.goal_belief_margin is not None and not (math.isfinite(self.goal_belief_margin)
                                                        and self.goal_belief_margin > 0):
            raise ValueError(f"goal_belief_margin must be None or a finite number > 0, got {self.goal_belief_margin}")
        if not (math.isfinite(self.prior_covariance_scale) and self.prior_covariance_scale > 0):
            raise ValueError(f"prior_covariance_scale must be a finite number > 0, got {self.prior_covariance_scale}")


FUSION_PRESETS: dict[str, dict[str, Any]] = {
    "tuned": dict(ood_covariance="predictive", ood_alpha=0.99, belief_memory=1.0, prior_covariance_scale=100.0,
                  uncommanded_axes="missing_unused", goal_belief_margin=1.0),
    "paper": dict(ood_covariance="class", ood_alpha=0.85, belief_memory=0.0, prior_covariance_scale=1.0,
                  uncommanded_axes="missing", goal_belief_margin=None),
}
"""Named fusion settings (:meth:`SharedControlConfig.preset`); ``"tuned"`` is the default."""


@dataclass
class SharedControlDiagnostics:
    """What happened in the last :meth:`SharedController.step` (B = batch size; B = 1 unbatched).

    Attributes:
        modes: per element one of ``"shared"``, ``"autonomous"``, ``"user_only"``.
        class_weights: ``(B, K)`` posterior class weights in shared mode, the prior's otherwise
            (empty ``(B, 0)`` when the policy was not called).
        prior_class_weights: ``(B, K)`` the prior's class weights.
        ood: ``(B,)`` bool, in the out-of-distribution window.
        surface_distance: ``(B,)`` EE distance to the nearest valid scene point (m; inf if none).
        user_trans_cov, user_rot_cov: ``(B, 3, 3)`` S_u and G_u used this step.
        fallback: ``(B,)`` bool, the empty-grasp-set fallback was used.
        shown_grasps: ``(B, M)`` bool, the candidates the prior was shown (see the field);
            grasp_candidates ``(B,)`` their number before the goal belief.
        mixture: the step-0 mixture behind ``class_weights`` (fused where shared, the prior's
            elsewhere); None when the policy was not called.

    The entropy bounds ``trans_entropy_lower``, ``trans_entropy_upper``, ``rot_entropy_lower``,
    ``rot_entropy_upper`` (``(B,)`` nats, NaN when the policy was not called) are computed from
    ``mixture`` when first read, so a control loop that does not look at them does not pay for them.
    """

    modes: tuple[str, ...]
    class_weights: torch.Tensor
    prior_class_weights: torch.Tensor
    ood: torch.Tensor
    surface_distance: torch.Tensor
    user_trans_cov: torch.Tensor
    user_rot_cov: torch.Tensor
    fallback: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.bool))
    mixture: posterior.FactorizedTwistMixture | None = None
    shown_grasps: torch.Tensor | None = None
    """``(B, M)`` bool, the grasp candidates the prior was shown (``goal_belief_margin``; None
    without grasp candidates in the observation)."""
    grasp_candidates: torch.Tensor | None = None
    """``(B,)`` the number of grasp candidates in the observation (None without any)."""

    @property
    def mode(self) -> str:
        """The mode of a single (unbatched or B = 1) step."""
        if len(self.modes) != 1:
            raise ValueError(f"batched step with {len(self.modes)} elements: use .modes")
        return self.modes[0]

    @cached_property
    def _entropy_bounds(self) -> tuple[torch.Tensor, ...]:
        if self.mixture is None:
            nan = torch.full((len(self.modes),), math.nan, dtype=torch.float64)
            return nan, nan.clone(), nan.clone(), nan.clone()
        return (*mixture_entropy.translation_entropy_bounds(self.mixture),
                *mixture_entropy.rotation_entropy_bounds(self.mixture))

    @property
    def trans_entropy_lower(self) -> torch.Tensor:
        return self._entropy_bounds[0]

    @property
    def trans_entropy_upper(self) -> torch.Tensor:
        return self._entropy_bounds[1]

    @property
    def rot_entropy_lower(self) -> torch.Tensor:
        return self._entropy_bounds[2]

    @property
    def rot_entropy_upper(self) -> torch.Tensor:
        return self._entropy_bounds[3]


def surface_distance(observation: dict[str, Any], table_height: float | None = None) -> torch.Tensor:
    """``(B,)`` distance (m) from the EE position (``observation.state[..., EE_POS]``, world) to the
    nearest valid point of ``observation.point_cloud`` (world xyz), or to the table top (the plane
    z = ``table_height``) where that is nearer; inf without either."""
    state = torch.as_tensor(observation[features.STATE])
    ee = (state[None] if state.ndim == 1 else state)[:, features.EE_POS].double()
    dist = _cloud_distance(observation, ee)
    return dist if table_height is None else torch.minimum(dist, ee[:, 2] - table_height)


def _cloud_distance(observation: dict[str, Any], ee: torch.Tensor) -> torch.Tensor:
    """``(B,)`` distance from ``ee (B, 3)`` to the nearest valid cloud point; inf without one."""
    b = ee.shape[0]
    if features.POINT_CLOUD not in observation:
        return torch.full((b,), math.inf, dtype=torch.float64)
    cloud = features.unflatten(features.POINT_CLOUD, torch.as_tensor(observation[features.POINT_CLOUD]))
    cloud = (cloud[None] if cloud.ndim == 2 else cloud)[..., :3].double()
    if cloud.shape[0] != b:
        raise ValueError(f"{features.POINT_CLOUD} has batch {cloud.shape[0]}, state has {b}")
    if features.POINT_CLOUD_MASK in observation:
        mask = torch.as_tensor(observation[features.POINT_CLOUD_MASK])
        mask = (mask[None] if mask.ndim == 1 else mask) > 0.5
    else:
        mask = torch.ones(cloud.shape[:2], dtype=torch.bool)
    mask = mask & torch.isfinite(cloud).all(-1)
    dist = (cloud - ee[:, None]).norm(dim=-1)
    dist = torch.where(mask, dist, torch.full_like(dist, math.inf))
    return dist.min(-1).values if dist.shape[1] > 0 else torch.full((b,), math.inf, dtype=torch.float64)


def most_likely_twist(prior: posterior.FactorizedTwistMixture) -> torch.Tensor:
    """The prior's most likely step-0 action ``(B, 6)``: the argmax class, the mean of its
    translation Gaussian, then the mean of its rotation Gaussian given that translation
    (docs/PAPER_DETAILS.md "Most-Likely"; the same as the policy's ``select_action``). ``prior`` is
    :func:`posterior.prior_twist_mixture`, whose rotation Gaussians already sit at the
    translation means, so no second pass through the network is needed."""
    best = prior.log_weights.argmax(-1)
    return prior.means[torch.arange(best.shape[0], device=best.device), best]


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
        """``(B, 6)`` axes the user has commanded since ``reset()`` (the device's axes; ``missing_far*``)."""
        self._user_cov: UserCovarianceEstimator | None = None
        self._evidence: torch.Tensor | None = None
        """``(B, K)`` accumulated log-likelihood of the user's commands per class (``belief_memory``)."""
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
        self._evidence = None
        self._goal_belief = self._make_goal_belief()
        self.last_diagnostics = None

    def _with_belief(self, mixture: TwistMixture) -> TwistMixture:
        """The prior's mixture with the accumulated evidence of earlier commands added to its class
        log-weights (recursive goal belief; unchanged when ``belief_memory`` is 0)."""
        if self.config.belief_memory == 0.0:
            return mixture
        lw = mixture.log_weights.double()
        if self._evidence is None or self._evidence.shape != lw.shape:
            self._evidence = torch.zeros_like(lw)
        lw = lw + self._evidence
        return dataclasses.replace(mixture, log_weights=lw - torch.logsumexp(lw, -1, keepdim=True))

    def _remember(self, shared: torch.Tensor, prior: posterior.FactorizedTwistMixture,
                  fused: posterior.FactorizedTwistMixture | None) -> None:
        """Decay the evidence and add this step's class log-likelihoods where it was shared."""
        if self.config.belief_memory == 0.0 or self._evidence is None:
            return
        gained = torch.zeros_like(self._evidence)
        if fused is not None:
            gained = torch.where(shared[:, None], fused.log_weights - prior.log_weights, gained)
        evidence = self.config.belief_memory * self._evidence + gained
        # Relative to the best class, floored: a user who changes their mind can still be followed.
        self._evidence = (evidence - evidence.max(-1, keepdim=True).values).clamp_min(-EVIDENCE_FLOOR)

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
                adapt=c.adapt_user_covariance,
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
        observed = commanded
        if c.uncommanded_axes == "zero":
            observed = torch.ones_like(commanded)
        elif c.uncommanded_axes != "missing":  # axes on the device hold still: near the scene, or anywhere
            used = self._commanded_axes
            used_kind = used.view(b, 2, 3).any(-1, keepdim=True).expand(b, 2, 3).reshape(b, 6)
            near = (dist <= c.autonomy_cutoff_distance)[:, None]
            if c.uncommanded_axes == "missing_far":
                observed = observed | (used & near)
            elif c.uncommanded_axes == "missing_far_group":
                observed = observed | (used_kind & near)
            elif c.uncommanded_axes == "missing_unused":
                observed = observed | used | (used_kind & near)
            else:  # missing_unused_group
                observed = observed | used_kind

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
            mixture = self._with_belief(mixture.scaled(c.prior_covariance_scale))
            fused = None
            fired = torch.zeros(b, dtype=torch.bool)
            if (active & ~no_grasps).any():
                prior, fused = posterior.prior_and_fused_mixtures(
                    mixture, user, s_u, g_u, c.reweight_rotation_at, observed=observed)
                fired = (active & ood_gate.is_out_of_distribution(fused, c.ood_alpha, c.ood_covariance, c.ood_dofs)
                         & ~no_grasps)
            else:
                prior = posterior.prior_twist_mixture(mixture)
            self._ood_remaining = torch.where(fired, torch.full_like(self._ood_remaining, c.ood_steps),
                                              self._ood_remaining)
            ood = (in_window | fired) & ~no_grasps
            shared = active & ~ood & ~no_grasps
            autonomous = ~active & ~ood & ~no_grasps & (dist > c.autonomy_cutoff_distance)
            if not c.asynchronous:
                autonomous = torch.zeros_like(autonomous)
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
            self._remember(shared, prior, fused)
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
