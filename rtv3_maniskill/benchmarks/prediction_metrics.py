"""Trajectory-prediction metrics (paper Table I, left half; docs/PAPER_DETAILS.md "Metrics").

Error per step: the paper's pose distance with ``E = T_gt^-1 T_pred``,
``||t_E||_1 + (0.3/pi) ||euler_xyz(E)||_1`` (m, rad), reported x1000. ADE = mean over the H
steps, FDE = last step. Best-of-Mode: the minimum over maneuver classes (ADE and FDE minimised
separately, as Trajectron++ does); Most-Likely: the class with the largest ``p(z|h0)``. Also the
two reference predictors a trained prior should beat, and the calibration of the prior's step-0
translation Gaussians. Poses are world-frame ``(4, 4)``; twists are body twists ``[v, w]``.
"""

from __future__ import annotations

from typing import Any

import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.shared_control import gaussians, ood_gate

METRIC_SCALE = 1000.0
"""The paper reports pose distances x1000."""
METRIC_NAMES = ("ade_bom", "fde_bom", "ade_ml", "fde_ml")
CALIBRATION_ALPHA = 0.85
"""The shared controller's OOD-gate quantile (docs/PAPER_DETAILS.md), used to check the prior's calibration."""


def displacement_errors(
    gt_poses: torch.Tensor, pred_poses: torch.Tensor, rot_weight: float = se3.PLANNING_ROT_WEIGHT
) -> torch.Tensor:
    """Per-step errors ``(..., H)`` x1000 between poses ``(..., H, 4, 4)`` (world frame).

    ``1000 * (||t_E||_1 + rot_weight * ||euler_xyz(E)||_1)`` with ``E = T_gt^-1 T_pred``
    (paper appendix "Distance Metric"). ``pred_poses`` may carry extra leading dims that
    broadcast against ``gt_poses`` (e.g. ``(B, K, H, 4, 4)`` vs ``(B, 1, H, 4, 4)``).
    """
    for name, value in (("gt_poses", gt_poses), ("pred_poses", pred_poses)):
        if value.ndim < 3 or tuple(value.shape[-2:]) != (4, 4):
            raise ValueError(f"{name} must be (..., H, 4, 4) homogeneous transforms, got {tuple(value.shape)}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name} contains NaN or inf")
    return METRIC_SCALE * se3.pose_distance(gt_poses, pred_poses, rot_weight)


def ade_fde(errors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``errors (..., H)`` -> (ADE = mean over the horizon, FDE = last step), each ``(...)``."""
    if errors.ndim < 1 or errors.shape[-1] == 0:
        raise ValueError(f"errors must be (..., H) with H >= 1, got {tuple(errors.shape)}")
    return errors.mean(-1), errors[..., -1]


def future_poses(current: torch.Tensor, twists: torch.Tensor, dt: float = features.DT) -> torch.Tensor:
    """Poses ``(B, [K,] H, 4, 4)`` reached from ``current (B, 4, 4)`` by body twists ``(B, [K,] H, 6)``."""
    if current.ndim != 3 or tuple(current.shape[1:]) != (4, 4):
        raise ValueError(f"current must be (B, 4, 4), got {tuple(current.shape)}")
    if twists.shape[-1] != 6 or twists.ndim not in (3, 4) or twists.shape[0] != current.shape[0]:
        raise ValueError(f"twists must be (B, [K,] H, 6) with B = {current.shape[0]}, got {tuple(twists.shape)}")
    start = current if twists.ndim == 3 else current[:, None].expand(-1, twists.shape[1], 4, 4)
    return se3.integrate_body_twists(start, twists.to(current.dtype), dt)


def mode_metrics(gt_poses: torch.Tensor, mode_poses: torch.Tensor, log_prior: torch.Tensor) -> dict[str, torch.Tensor]:
    """Best-of-Mode and Most-Likely ADE/FDE per window (x1000).

    Args:
        gt_poses: ``(B, H, 4, 4)`` recorded future poses.
        mode_poses: ``(B, K, H, 4, 4)`` most likely future of each maneuver class.
        log_prior: ``(B, K)`` log p(z|h0).

    Returns ``ade_bom, fde_bom, ade_ml, fde_ml`` ``(B,)`` and ``errors_ml`` ``(B, H)``.
    """
    if mode_poses.ndim != 5 or mode_poses.shape[0] != gt_poses.shape[0] or mode_poses.shape[2:] != gt_poses.shape[1:]:
        raise ValueError(
            f"mode_poses must be (B, K, H, 4, 4) matching gt_poses {tuple(gt_poses.shape)}, "
            f"got {tuple(mode_poses.shape)}"
        )
    if tuple(log_prior.shape) != tuple(mode_poses.shape[:2]):
        raise ValueError(f"log_prior must be (B, K) = {tuple(mode_poses.shape[:2])}, got {tuple(log_prior.shape)}")
    errors = displacement_errors(gt_poses[:, None], mode_poses)  # (B, K, H)
    ade, fde = ade_fde(errors)
    best = log_prior.argmax(-1)
    rows = torch.arange(errors.shape[0], device=errors.device)
    return dict(
        ade_bom=ade.min(-1).values,
        fde_bom=fde.min(-1).values,
        ade_ml=ade[rows, best],
        fde_ml=fde[rows, best],
        errors_ml=errors[rows, best],
    )


BASELINES = ("stand_still", "constant_velocity")


def baseline_twists(current_state: torch.Tensor, horizon: int) -> dict[str, torch.Tensor]:
    """Reference predictors from the current state ``(B, 27)``: twists ``(B, H, 6)``.

    ``stand_still``: zero twist; ``constant_velocity``: the body twist realised over the last
    step, repeated. A trained prior should beat both.
    """
    last = current_state[:, features.EE_TWIST]
    return dict(
        stand_still=torch.zeros(last.shape[0], horizon, 6, dtype=last.dtype),
        constant_velocity=last[:, None].expand(-1, horizon, 6),
    )


def step0_calibration(mixture: Any, true_translation: torch.Tensor,
                      alpha: float = CALIBRATION_ALPHA) -> dict[str, torch.Tensor]:
    """How well the step-0 translation Gaussians cover the expert's next translation velocity.

    Args:
        mixture: the prior's ``TwistMixture`` (B windows, K classes; m/s, EE body frame).
        true_translation: ``(B, 3)`` the recorded velocity of the next step (same frame and units).
    Returns per window ``(B,)``: ``maha_sq_ml`` the squared Mahalanobis distance under the most
    likely class; ``covered_ml`` / ``covered_any`` whether it is within ``chi2.ppf(alpha, 3)``
    of that class / of the nearest class (the latter is the shared controller's OOD test with a
    perfect user: a calibrated prior covers ~``alpha``); ``nll`` the mixture's negative
    log-likelihood (nats); ``sigma_ml`` the geometric-mean standard deviation of the ML class (m/s).
    """
    threshold = ood_gate.ood_threshold(alpha, 3)
    mu, cov = mixture.trans_mean.double(), mixture.trans_cov.double()
    true_v = true_translation.double()[:, None]  # (B, 1, 3) against K classes
    maha = gaussians.mahalanobis_sq(true_v, mu, cov)  # (B, K)
    log_n = gaussians.gaussian_log_prob(true_v, mu, cov)
    log_det = torch.linalg.slogdet(cov)[1]
    best = mixture.log_weights.argmax(-1)
    rows = torch.arange(best.shape[0])
    return dict(
        maha_sq_ml=maha[rows, best],
        covered_ml=maha[rows, best] <= threshold,
        covered_any=maha.min(-1).values <= threshold,
        nll=-torch.logsumexp(mixture.log_weights.double() + log_n, -1),
        sigma_ml=torch.exp(log_det[rows, best] / 6.0),
    )
