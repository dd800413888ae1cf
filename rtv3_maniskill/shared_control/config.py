"""Settings of the RT-V3 shared controller (paper, Sec. V) and its named fusion presets.

Units: m, m/s, rad/s. :data:`FUSION_PRESETS` holds the fusions the benchmark runs: ``"tuned"`` (the
defaults), ``"tuned_ycb"`` (the same, trusting the prior more) and ``"paper"`` (the paper's reading).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from rtv3_maniskill.shared_control import ood_gate
from rtv3_maniskill.shared_control.command_axes import UNCOMMANDED_AXES
from rtv3_maniskill.shared_control.twist_utils import check_speed_limits


@dataclass
class SharedControlConfig:
    """Settings of :class:`~rtv3_maniskill.shared_control.shared_controller.SharedController`.
    Units: m, m/s, rad/s; :meth:`preset` gives the named fusions."""

    max_linear_speed: float | None = 0.5
    """Norm limit on the executed translation velocity (m/s); None = no limit."""
    max_angular_speed: float | None = 1.5
    """Norm limit on the executed rotation velocity (rad/s); None = no limit."""
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
    "distance to the nearest class", the paper's reading); the test looks at the command's observed
    translation and rotation axes (:func:`~rtv3_maniskill.shared_control.ood_gate.is_out_of_distribution`)."""
    uncommanded_axes: str = "missing_unused"
    """How a zero axis (``|u_i| <= input_threshold``) of a command that is not zero altogether is
    read: ``"missing"``, an axis the device does not give, so neither the fusion nor the OOD test
    uses it and the prior fills it in; ``"missing_unused"``, missing only while the user has never
    commanded that axis and the EE is farther than ``autonomy_cutoff_distance`` from the scene,
    "hold still" on an axis the user has commanded and then left, and near the scene on every
    axis of a kind (translation or rotation) the user has commanded
    (:mod:`~rtv3_maniskill.shared_control.command_axes`)."""
    user_trans_var: float = 0.03
    """Initial S_u diagonal ((m/s)^2)."""
    user_rot_var: float = 0.1
    """Initial G_u diagonal ((rad/s)^2)."""
    user_cov_window: int = 14
    """Recent commands the user covariance is estimated from
    (:class:`~rtv3_maniskill.shared_control.user_covariance.UserCovarianceEstimator`)."""
    user_cov_decay: float = 0.8
    """Weight of the current user covariance in each update (1: S_u and G_u stay at their initial values)."""
    user_cov_floor: float = 0.01
    """Least geometric-mean variance of S_u and G_u."""
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
    and hands the prior only the candidates within this many nats of the most likely one (with
    fewer candidates the prior turns the hand towards the grasp the user drives to)."""
    prior_covariance_scale: float = 100.0
    """Factor on the prior's step-0 covariances (Sigma_z and Gamma_z) before the gate and the
    fusion. 1 (the paper) takes the prior as calibrated; a larger factor gives the user's command
    more weight (Kalman gain ``K = s Sigma_z (s Sigma_z + S_u)^-1``) where the prior is overconfident,
    e.g. on states its own closed loop leads it to (`rtv3 evaluate prediction` reports a prior's
    step-0 coverage)."""
    mode_search_starts: int = 3
    """Component means the mode search starts from (:func:`mode_search.mixture_mode`)."""
    mode_search_iters: int = 10
    """Most mean-shift iterations of the mode search (:func:`mode_search.mixture_mode`)."""
    mode_search_tol: float = 1e-6
    """Stop the mode search once no iterate moves by more than this (m/s, rad/s)."""

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> SharedControlConfig:
        """A named fusion (:data:`FUSION_PRESETS`), with ``overrides`` on top.

        ``"tuned"`` (the defaults, chosen on the easy preset's validation scenes): the gate under the
        predictive covariance at alpha 0.99, a recursive belief over the classes and over the grasp
        candidates, the prior's covariances times 100 and a command's zero axes held still on axes the
        user has left (``missing_unused``); ``"tuned_ycb"`` (chosen on the paper preset's YCB packed
        validation scenes): the same with the prior's covariances times 30, so the fused twist leans
        more on the prior and filters more of a noisy user's command; ``"paper"``, the paper's
        reading: the gate under the class covariance at alpha 0.85, no memory of earlier commands,
        every candidate shown, the prior's covariances as predicted and a command's zero axes missing
        everywhere.
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
        if self.uncommanded_axes not in UNCOMMANDED_AXES:
            raise ValueError(f"uncommanded_axes must be one of {UNCOMMANDED_AXES}, got {self.uncommanded_axes!r}")
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


_TUNED: dict[str, Any] = dict(ood_covariance="predictive", ood_alpha=0.99, belief_memory=1.0,
                              prior_covariance_scale=100.0, uncommanded_axes="missing_unused", goal_belief_margin=1.0)

FUSION_PRESETS: dict[str, dict[str, Any]] = {
    "tuned": _TUNED,
    "tuned_ycb": {**_TUNED, "prior_covariance_scale": 30.0},
    "paper": dict(ood_covariance="class", ood_alpha=0.85, belief_memory=0.0, prior_covariance_scale=1.0,
                  uncommanded_axes="missing", goal_belief_margin=None),
}
"""Named fusion settings (:meth:`SharedControlConfig.preset`); ``"tuned"`` is the default."""
