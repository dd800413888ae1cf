"""Entropy bounds of the step-0 twist mixture, the paper's "Trans Entropy" / "Rot Entropy" (Sec. V).

Diagnostics only: the controller reports them (:class:`~rtv3_maniskill.shared_control.diagnostics.
SharedControlDiagnostics`), nothing it executes depends on them.
"""

from __future__ import annotations

import torch

from rtv3_maniskill.shared_control.gaussians import (
    gaussian_entropy,
    gaussian_log_prob,
    normalize_log_weights,
    regularize_covariance,
)
from rtv3_maniskill.shared_control.posterior import FactorizedTwistMixture


def mixture_entropy_bounds(
    log_weights: torch.Tensor, means: torch.Tensor, covs: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds ``(B,), (B,)`` (nats) on the entropy of a Gaussian mixture.

    ``log_weights (B, K)``, ``means (B, K, D)``, ``covs (B, K, D, D)``. Huber et al. 2008:
    upper ``sum_k pi_k (H(N_k) - log pi_k)``; lower
    ``-sum_i pi_i log sum_j pi_j N(m_i; m_j, C_i + C_j)``.
    """
    lw = normalize_log_weights(log_weights.double())
    w = lw.exp()
    covs = covs.double()
    means = means.double()
    safe_lw = torch.where(w > 0, lw, torch.zeros_like(lw))
    upper = (w * (gaussian_entropy(covs) - safe_lw)).sum(-1)
    pair_cov = regularize_covariance(covs[:, :, None] + covs[:, None, :])  # (B, K, K, D, D)
    pair_lp = gaussian_log_prob(means[:, :, None], means[:, None, :], pair_cov)  # (B, K, K)
    lower = -(w * torch.logsumexp(lw[:, None, :] + pair_lp, -1)).sum(-1)
    return lower, upper


def translation_entropy_bounds(mixture: FactorizedTwistMixture) -> tuple[torch.Tensor, torch.Tensor]:
    """Entropy bounds ``(B,), (B,)`` of the translation marginal (the paper's "Trans Entropy")."""
    return mixture_entropy_bounds(mixture.log_weights, mixture.trans_mean, mixture.trans_cov)


def rotation_entropy_bounds(mixture: FactorizedTwistMixture) -> tuple[torch.Tensor, torch.Tensor]:
    """Entropy bounds ``(B,), (B,)`` of the rotation marginal, each class's rotation Gaussian
    taken at its (fused) translation mean."""
    return mixture_entropy_bounds(mixture.log_weights, mixture.rot_mean, mixture.rot_cov)
