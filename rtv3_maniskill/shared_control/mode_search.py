"""The executed action of shared mode: the mode of the posterior step-0 twist mixture (paper, Sec. V).

The paper executes the most probable twist under the fused mixture
``sum_k pi_k' N(v; mu_k', Sigma_k') N(w; omega_k', Gamma_k')`` (B batch, K classes, 6-D
``[v (m/s), w (rad/s)]``, EE body frame). :func:`mixture_mode` finds it by Gaussian mean-shift
from the best component means.
"""

from __future__ import annotations

import math

import torch

from rtv3_maniskill.shared_control.gaussians import LOG_2PI
from rtv3_maniskill.shared_control.posterior import FactorizedTwistMixture


def _whitened_components(m: FactorizedTwistMixture) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-class whitening of the 6-D mixture, computed once per mixture.

    Returns ``W (B, K, 6, 6)`` block-diagonal with ``W_k^T W_k = P_k`` (the class precision;
    ``W_k = blockdiag(L_v^-1, L_w^-1)`` from the Cholesky factors) and ``log_norm (B, K) =
    log pi_k - 3 log 2pi - log det L_k``, so that ``log pi_k + log N_k(x) = log_norm_k -
    0.5 |W_k (x - m_k)|^2``.
    """
    b, k = m.log_weights.shape
    eye = torch.eye(3, dtype=m.trans_cov.dtype, device=m.trans_cov.device)
    whiten = m.trans_cov.new_zeros(b, k, 6, 6)
    log_det = m.log_weights.new_zeros(b, k)
    for block, cov in ((slice(0, 3), m.trans_cov), (slice(3, 6), m.rot_cov)):
        chol = torch.linalg.cholesky(cov)
        whiten[..., block, block] = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
        log_det = log_det + torch.diagonal(chol, dim1=-2, dim2=-1).log().sum(-1)
    return whiten, m.log_weights - 3.0 * LOG_2PI - log_det


def _component_log_densities(
    x: torch.Tensor, m: FactorizedTwistMixture, whitened: tuple[torch.Tensor, torch.Tensor] | None = None
) -> torch.Tensor:
    """``x (B, S, 6)`` -> ``(B, S, K)`` ``log pi_k + log N_k(x)``."""
    whiten, log_norm = _whitened_components(m) if whitened is None else whitened
    diff = x[:, :, None, :] - m.means[:, None]  # (B, S, K, 6)
    white = torch.einsum("bkij,bskj->bski", whiten, diff)
    return log_norm[:, None] - 0.5 * (white * white).sum(-1)


def mixture_log_density(x: torch.Tensor, mixture: FactorizedTwistMixture) -> torch.Tensor:
    """Log density of the 6-D mixture at ``x (B, S, 6)`` -> ``(B, S)``."""
    return torch.logsumexp(_component_log_densities(x.double(), mixture), -1)


def mixture_mode(
    mixture: FactorizedTwistMixture, num_starts: int = 3, num_iters: int = 10, tol: float = 1e-6
) -> torch.Tensor:
    """Approximate mode ``(B, 6)`` of the 6-D mixture (the executed action).

    The authors grid-search the mode. Here: evaluate the mixture density at every
    component mean, start from the ``num_starts`` best means, and run ``num_iters``
    fixed-point (Gaussian mean-shift) iterations
    ``x <- (sum_k r_k(x) P_k)^-1 sum_k r_k(x) P_k m_k`` (``r_k`` responsibilities,
    ``P_k`` precisions), whose fixed points are the stationary points of the density; the
    iteration stops early once no iterate moves by more than ``tol`` (m/s, rad/s; with the
    shipped prior that takes 2-3 iterations).
    The highest-density point among the start means and the iterates is returned, so
    the result is never worse than the best component mean.
    """
    if num_starts < 1 or num_iters < 0 or not tol >= 0:
        raise ValueError(f"need num_starts >= 1, num_iters >= 0, tol >= 0; got {num_starts}, {num_iters}, {tol}")
    means = mixture.means  # (B, K, 6)
    b, k, _ = means.shape
    whitened = _whitened_components(mixture)  # factorised once, reused by every iteration
    at_means_components = _component_log_densities(means, mixture, whitened)  # (B, K, K)
    at_means = torch.logsumexp(at_means_components, -1)  # (B, K)
    s = min(num_starts, k)
    start_density, start_idx = at_means.topk(s, dim=-1)  # (B, S)
    x = torch.gather(means, 1, start_idx[..., None].expand(b, s, 6))
    component = torch.gather(at_means_components, 1, start_idx[..., None].expand(b, s, k))  # (B, S, K) at x
    candidates, densities = [x], [start_density]
    precisions = whitened[0].transpose(-1, -2) @ whitened[0]  # P_k = W_k^T W_k, (B, K, 6, 6)
    prec_means = (precisions @ means.unsqueeze(-1)).squeeze(-1)  # (B, K, 6)
    for _ in range(num_iters):
        resp = torch.softmax(component, -1)  # responsibilities r_k(x), (B, S, K)
        a = torch.einsum("bsk,bkij->bsij", resp, precisions)
        rhs = torch.einsum("bsk,bki->bsi", resp, prec_means)
        x_next = torch.linalg.solve(a, rhs.unsqueeze(-1)).squeeze(-1)
        converged = bool(((x_next - x).abs() <= tol).all())
        x = x_next
        component = _component_log_densities(x, mixture, whitened)
        candidates.append(x)
        densities.append(torch.logsumexp(component, -1))
        if converged:
            break
    cand = torch.cat(candidates, 1)  # (B, S*(iters+1), 6)
    dens = torch.cat(densities, 1)
    dens = torch.where(torch.isfinite(dens), dens, torch.full_like(dens, -math.inf))
    best = dens.argmax(-1)
    return cand[torch.arange(b), best]
