"""Gaussian algebra of the posterior (paper, Sec. V): densities, Mahalanobis distances, entropy
and the Kalman update of Eq. K_v / K_w.

All functions work on batched ``(..., D)`` vectors and ``(..., D, D)`` covariances. The posterior
runs them in float64; :func:`regularize_covariance` symmetrises a covariance and clamps its
eigenvalues to ``[MIN_VARIANCE, MAX_VARIANCE]`` so that no step can produce NaN from a
near-singular network output.
"""

from __future__ import annotations

import math

import torch

MIN_VARIANCE = 1e-8
"""Eigenvalue floor for every covariance (units m^2/s^2 or rad^2/s^2)."""
MAX_VARIANCE = 1e6
"""Eigenvalue ceiling for every covariance; also the variance of a missing command axis."""

LOG_2PI = math.log(2 * math.pi)


def regularize_covariance(cov: torch.Tensor, min_var: float = MIN_VARIANCE,
                          max_var: float = MAX_VARIANCE) -> torch.Tensor:
    """Symmetrise ``(..., D, D)`` and clamp its eigenvalues to ``[min_var, max_var]``."""
    sym = 0.5 * (cov + cov.transpose(-1, -2))
    eigval, eigvec = torch.linalg.eigh(sym)
    eigval = eigval.clamp(min_var, max_var)
    return (eigvec * eigval[..., None, :]) @ eigvec.transpose(-1, -2)


def gaussian_log_prob_and_mahalanobis_sq(
    x: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(log N(x; mean, cov), (x - mean)^T cov^-1 (x - mean))`` from one Cholesky factorisation.

    ``x, mean (..., D)``, ``cov (..., D, D)`` SPD -> two ``(...)`` tensors.
    """
    chol = torch.linalg.cholesky(cov)
    white = torch.linalg.solve_triangular(chol, (x - mean).unsqueeze(-1), upper=False).squeeze(-1)
    maha = (white * white).sum(-1)
    half_logdet = torch.diagonal(chol, dim1=-2, dim2=-1).log().sum(-1)
    return -0.5 * (x.shape[-1] * LOG_2PI + maha) - half_logdet, maha


def gaussian_log_prob(x: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """``log N(x; mean, cov)`` for ``x, mean (..., D)``, ``cov (..., D, D)`` SPD -> ``(...)``."""
    return gaussian_log_prob_and_mahalanobis_sq(x, mean, cov)[0]


def mahalanobis_sq(x: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """Squared Mahalanobis distance ``(x - mean)^T cov^-1 (x - mean)`` -> ``(...)``."""
    return gaussian_log_prob_and_mahalanobis_sq(x, mean, cov)[1]


def gaussian_entropy(cov: torch.Tensor) -> torch.Tensor:
    """Differential entropy ``0.5 log det(2 pi e cov)`` of ``(..., D, D)`` -> ``(...)`` nats."""
    dim = cov.shape[-1]
    return 0.5 * (dim * (1.0 + LOG_2PI) + torch.linalg.slogdet(cov)[1])


def kalman_update(
    mean: torch.Tensor, cov: torch.Tensor, observation: torch.Tensor, observation_cov: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Kalman update of ``N(mean, cov)`` with a direct observation ``N(observation; x, observation_cov)``.

    Shapes ``(..., D)`` / ``(..., D, D)``. Returns ``(mean', cov', kalman_gain)`` with
    ``kalman_gain = cov (cov + observation_cov)^-1`` (paper Eq. K_v / K_w). The covariance
    uses the Joseph form ``(I-K) cov (I-K)^T + K R K^T``, algebraically equal to the paper's
    ``(I - K) cov`` but symmetric positive definite in floating point.
    """
    innovation_cov = cov + observation_cov
    # cov and innovation_cov are symmetric: K = cov S^-1 = (S^-1 cov)^T.
    kalman_gain = torch.linalg.solve(innovation_cov, cov).transpose(-1, -2)
    new_mean = mean + (kalman_gain @ (observation - mean).unsqueeze(-1)).squeeze(-1)
    eye = torch.eye(mean.shape[-1], dtype=mean.dtype, device=mean.device)
    i_minus_k = eye - kalman_gain
    new_cov = (i_minus_k @ cov @ i_minus_k.transpose(-1, -2)
               + kalman_gain @ observation_cov @ kalman_gain.transpose(-1, -2))
    return new_mean, regularize_covariance(new_cov), kalman_gain


def normalize_log_weights(log_weights: torch.Tensor) -> torch.Tensor:
    """``(..., K)`` log-weights shifted so that their logsumexp over the last axis is 0."""
    return log_weights - torch.logsumexp(log_weights, -1, keepdim=True)
