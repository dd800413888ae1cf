"""Posterior decision making: fuse a user command with the prior's step-0 twist mixture.

Paper, Sec. "Posterior Decision Making". Per maneuver class ``k`` (B batch, K classes):

* translation (Eq. K_v):   ``kalman_gain = Sigma_k (Sigma_k + S_u)^-1``,
  ``mu_k' = mu_k + K (v_u - mu_k)``, ``Sigma_k' = (I - K) Sigma_k``;
* rotation, conditioned on the fused translation (Eq. K_w): ``(omega_k, Gamma_k) =
  rotation_given_translation(mu_k')``, then the same update with ``w_u`` and ``G_u``;
* class weights (Eq. p(z | h_0, a_0^u)):
  ``pi_k' ∝ pi_k N(v_u; mu_k, Sigma_k + S_u) N(w_u; omega_k, Gamma_k + G_u)``.

Reading of the class weights. The paper writes the class likelihood with the *prior*
component ``N(v_u; mu_z, Sigma_z) N(w_u; omega_z, Gamma_z)``; docs/PAPER_DETAILS.md (authors' code)
writes the rotation term at the fused translation ``omega_k'``. We follow the paper's
choice of the prior component (rotation Gaussian evaluated at the prior translation mean
``mu_k``, ``reweight_rotation_at="prior"``, the default) and add the user covariance to
both terms, which is the exact marginal ``∫ N(u; a, S_u) N(a; mu, Sigma) da`` under the
paper's own likelihood model ``p(u | a) = N(u; a, Sigma_sys)``. ``"fused"`` gives the
docs/PAPER_DETAILS.md variant.

All computation runs in float64; inputs may be float32. Covariances are symmetrised and
their eigenvalues clamped to ``[MIN_VARIANCE, MAX_VARIANCE]`` before use, so no step can
produce NaN from a near-singular network output.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from rtv3_maniskill.twist_mixture import TwistMixture

MIN_VARIANCE = 1e-8
"""Eigenvalue floor for every covariance (units m^2/s^2 or rad^2/s^2)."""
MAX_VARIANCE = 1e6
"""Eigenvalue ceiling for every covariance."""

_LOG_2PI = math.log(2 * math.pi)


# --------------------------------------------------------------------------- Gaussians


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
    return -0.5 * (x.shape[-1] * _LOG_2PI + maha) - half_logdet, maha


def gaussian_log_prob(x: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """``log N(x; mean, cov)`` for ``x, mean (..., D)``, ``cov (..., D, D)`` SPD -> ``(...)``."""
    return gaussian_log_prob_and_mahalanobis_sq(x, mean, cov)[0]


def mahalanobis_sq(x: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """Squared Mahalanobis distance ``(x - mean)^T cov^-1 (x - mean)`` -> ``(...)``."""
    return gaussian_log_prob_and_mahalanobis_sq(x, mean, cov)[1]


def gaussian_entropy(cov: torch.Tensor) -> torch.Tensor:
    """Differential entropy ``0.5 log det(2 pi e cov)`` of ``(..., D, D)`` -> ``(...)`` nats."""
    dim = cov.shape[-1]
    return 0.5 * (dim * (1.0 + _LOG_2PI) + torch.linalg.slogdet(cov)[1])


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


# --------------------------------------------------------------------------- mixtures


@dataclass
class FactorizedTwistMixture:
    """A step-0 twist mixture with the rotation Gaussian fixed per class (B batch, K classes).

    Each class is ``N(v; trans_mean_k, trans_cov_k) N(w; rot_mean_k, rot_cov_k)``. For the
    posterior, the rotation Gaussian is the one conditioned on the fused translation mean
    (a first-order reading of the paper's translation-conditioned rotation). float64.

    Attributes:
        log_weights: ``(B, K)`` normalised log class probabilities.
        trans_mean, trans_cov: ``(B, K, 3)``, ``(B, K, 3, 3)`` in m/s, EE body frame.
        rot_mean, rot_cov: ``(B, K, 3)``, ``(B, K, 3, 3)`` in rad/s, EE body frame.
        prior_log_weights: ``(B, K)`` the prior's class log-probabilities (before fusion).
        trans_mahalanobis_sq: ``(B, K)`` squared Mahalanobis distance of the user translation
            to each class under ``Sigma_k + S_u`` (``None`` for a prior-only mixture).
        rot_mahalanobis_sq: ``(B, K)`` squared Mahalanobis distance of the user rotation to each
            class's rotation Gaussian of the class likelihood, under ``Gamma_k + G_u``.
        trans_class_mahalanobis_sq, rot_class_mahalanobis_sq: the same two under the class
            covariances ``Sigma_k`` / ``Gamma_k`` alone. All four ``None`` for a prior-only mixture.
        observed: ``(B, 6)`` bool, the command's axes that were fused (the others were treated
            as missing; ``None`` for a prior-only mixture).
    """

    log_weights: torch.Tensor
    trans_mean: torch.Tensor
    trans_cov: torch.Tensor
    rot_mean: torch.Tensor
    rot_cov: torch.Tensor
    prior_log_weights: torch.Tensor
    trans_mahalanobis_sq: torch.Tensor | None = None
    rot_mahalanobis_sq: torch.Tensor | None = None
    trans_class_mahalanobis_sq: torch.Tensor | None = None
    rot_class_mahalanobis_sq: torch.Tensor | None = None
    observed: torch.Tensor | None = None

    @property
    def weights(self) -> torch.Tensor:
        """``(B, K)`` class probabilities."""
        return self.log_weights.exp()

    @property
    def means(self) -> torch.Tensor:
        """``(B, K, 6)`` ``[v, w]`` component means."""
        return torch.cat([self.trans_mean, self.rot_mean], -1)


def _check_mixture(mixture: TwistMixture) -> tuple[int, int]:
    lw, mu, cov = mixture.log_weights, mixture.trans_mean, mixture.trans_cov
    if lw.ndim != 2:
        raise ValueError(f"TwistMixture.log_weights must be (B, K), got {tuple(lw.shape)}")
    b, k = lw.shape
    if k == 0:
        raise ValueError("TwistMixture has no classes (K = 0)")
    if mu.shape != (b, k, 3) or cov.shape != (b, k, 3, 3):
        raise ValueError(
            f"TwistMixture shapes disagree: log_weights {tuple(lw.shape)}, trans_mean {tuple(mu.shape)} "
            f"(expected {(b, k, 3)}), trans_cov {tuple(cov.shape)} (expected {(b, k, 3, 3)})"
        )
    for name, t in (("log_weights", lw), ("trans_mean", mu), ("trans_cov", cov)):
        if torch.isnan(t).any() or (name != "log_weights" and not torch.isfinite(t).all()):
            raise ValueError(f"TwistMixture.{name} contains NaN or inf")
    if not torch.isfinite(torch.logsumexp(lw, -1)).all():
        raise ValueError("TwistMixture.log_weights are all -inf (or +inf) for some batch element")
    return b, k


def _rotation_at(mixture: TwistMixture, translation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Call ``rotation_given_translation`` at ``translation (..., B, K, 3)`` (leading dimensions:
    several translations per class, one call) and validate/regularise its output (float64)."""
    shape = tuple(translation.shape[:-1])
    dtype = mixture.trans_mean.dtype
    omega, gamma = mixture.rotation_given_translation(translation.to(dtype))
    if tuple(omega.shape) != (*shape, 3) or tuple(gamma.shape) != (*shape, 3, 3):
        raise ValueError(
            f"rotation_given_translation must return {(*shape, 3)} and {(*shape, 3, 3)} for translations "
            f"{tuple(translation.shape)}, got {tuple(omega.shape)} and {tuple(gamma.shape)}"
        )
    if not (torch.isfinite(omega).all() and torch.isfinite(gamma).all()):
        raise ValueError("rotation_given_translation returned NaN or inf")
    return omega.double(), regularize_covariance(gamma.double())


def _normalize_log_weights(log_weights: torch.Tensor) -> torch.Tensor:
    return log_weights - torch.logsumexp(log_weights, -1, keepdim=True)


def _prior_translation(mixture: TwistMixture) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Normalised class log-weights ``(B, K)``, translation means and regularised covariances (float64)."""
    _check_mixture(mixture)
    lw = _normalize_log_weights(mixture.log_weights.double())
    return lw, mixture.trans_mean.double(), regularize_covariance(mixture.trans_cov.double())


def prior_twist_mixture(mixture: TwistMixture) -> FactorizedTwistMixture:
    """The prior step-0 mixture with each class's rotation Gaussian at its translation mean ``mu_k``."""
    lw, mu, sigma = _prior_translation(mixture)
    omega, gamma = _rotation_at(mixture, mu)
    return FactorizedTwistMixture(lw, mu, sigma, omega, gamma, lw.clone())


def fuse_user_command(
    mixture: TwistMixture,
    user_twist: torch.Tensor,
    user_trans_cov: torch.Tensor,
    user_rot_cov: torch.Tensor,
    reweight_rotation_at: str = "prior",
    prior: FactorizedTwistMixture | None = None,
    observed: torch.Tensor | None = None,
) -> FactorizedTwistMixture:
    """Posterior step-0 mixture given the user command (paper, Sec. Posterior Decision Making).

    Args:
        mixture: the prior's step-0 mixture, B batch, K classes.
        user_twist: ``(B, 6)`` user command ``[v_u, w_u]``, EE body frame.
        user_trans_cov: ``(B, 3, 3)`` ``S_u`` (the paper's Sigma^sys).
        user_rot_cov: ``(B, 3, 3)`` ``G_u`` (the paper's Gamma^sys).
        reweight_rotation_at: ``"prior"`` (paper: rotation term of the class likelihood at
            ``omega_k(mu_k)``) or ``"fused"`` (docs/PAPER_DETAILS.md: at ``omega_k(mu_k')``).
        prior: optional :func:`prior_twist_mixture` of the same ``mixture``; its class weights,
            translation Gaussians and rotation Gaussians are reused instead of recomputed.
        observed: optional ``(B, 6)`` bool, the axes of the command that carry an observation
            (default: all). An unobserved axis is a missing measurement, not a zero one: the
            user covariance gets an infinite variance (``MAX_VARIANCE``) along it and no
            correlation with the other axes, so the Kalman gain, the class likelihood and the
            OOD distances ignore it (exactly, up to ``1 / MAX_VARIANCE``).
    Returns:
        The fused mixture; ``log_weights`` are ``log pi_k'``.
    """
    return _prior_and_fused(mixture, user_twist, user_trans_cov, user_rot_cov, reweight_rotation_at, prior, observed)[1]


def prior_and_fused_mixtures(
    mixture: TwistMixture,
    user_twist: torch.Tensor,
    user_trans_cov: torch.Tensor,
    user_rot_cov: torch.Tensor,
    reweight_rotation_at: str = "prior",
    observed: torch.Tensor | None = None,
) -> tuple[FactorizedTwistMixture, FactorizedTwistMixture]:
    """``(prior_twist_mixture(mixture), fuse_user_command(mixture, ...))`` with the rotation Gaussians
    at the prior means ``mu_k`` and at the fused means ``mu_k'`` from one call of
    ``rotation_given_translation`` (one pass through the network's rotation head per step)."""
    return _prior_and_fused(mixture, user_twist, user_trans_cov, user_rot_cov, reweight_rotation_at, None, observed)


def _prior_and_fused(
    mixture: TwistMixture,
    user_twist: torch.Tensor,
    user_trans_cov: torch.Tensor,
    user_rot_cov: torch.Tensor,
    reweight_rotation_at: str,
    prior: FactorizedTwistMixture | None,
    observed: torch.Tensor | None,
) -> tuple[FactorizedTwistMixture, FactorizedTwistMixture]:
    """See :func:`fuse_user_command`; also returns the prior mixture (``prior`` if given)."""
    if prior is not None:  # already checked, normalised and regularised by prior_twist_mixture
        prior_lw, mu, sigma = prior.prior_log_weights, prior.trans_mean, prior.trans_cov
    else:
        prior_lw, mu, sigma = _prior_translation(mixture)
    b, k = prior_lw.shape
    if reweight_rotation_at not in ("prior", "fused"):
        raise ValueError(f"reweight_rotation_at must be 'prior' or 'fused', got {reweight_rotation_at!r}")
    user = user_twist.double()
    if user.shape != (b, 6):
        raise ValueError(f"user_twist must be ({b}, 6) to match the mixture, got {tuple(user.shape)}")
    if not torch.isfinite(user).all():
        raise ValueError("user_twist contains NaN or inf")
    for name, c in (("user_trans_cov", user_trans_cov), ("user_rot_cov", user_rot_cov)):
        if c.shape != (b, 3, 3):
            raise ValueError(f"{name} must be ({b}, 3, 3), got {tuple(c.shape)}")
        if not torch.isfinite(c).all():
            raise ValueError(f"{name} contains NaN or inf")
    if observed is None:
        observed = torch.ones(b, 6, dtype=torch.bool, device=user.device)
    elif observed.shape != (b, 6) or observed.dtype != torch.bool:
        raise ValueError(f"observed must be a ({b}, 6) bool tensor, got {tuple(observed.shape)} {observed.dtype}")
    s_u, missing_v = _missing_axes_covariance(regularize_covariance(user_trans_cov.double()), observed[:, :3])
    g_u, missing_w = _missing_axes_covariance(regularize_covariance(user_rot_cov.double()), observed[:, 3:])
    s_u, g_u = s_u[:, None].expand(b, k, 3, 3), g_u[:, None].expand(b, k, 3, 3)
    missing_v, missing_w = missing_v[:, None], missing_w[:, None]
    v_u = user[:, None, :3].expand(b, k, 3)
    w_u = user[:, None, 3:].expand(b, k, 3)

    # Translation: Kalman fusion per class (Eq. K_v).
    mu_f, sigma_f, _ = kalman_update(mu, sigma, v_u, s_u)
    # Rotation conditioned on the fused translation (Eq. rotgmm at mu_k'), with the prior's at mu_k
    # in the same call when the prior mixture is not given.
    if prior is None:
        omega, gamma = _rotation_at(mixture, torch.stack([mu, mu_f]))
        prior = FactorizedTwistMixture(prior_lw, mu, sigma, omega[0], gamma[0], prior_lw.clone())
        omega_f, gamma_f = omega[1], gamma[1]
    else:
        omega_f, gamma_f = _rotation_at(mixture, mu_f)
    # ... then fused with w_u (Eq. K_w).
    omega_post, gamma_post = kalman_update(omega_f, gamma_f, w_u, g_u)[:2]

    # Class re-weighting (Eq. p(z | h_0, a_0^u)), in log space.
    # Sums of two regularised SPD matrices are SPD: no second eigen-decomposition needed.
    log_lik_v, trans_maha = gaussian_log_prob_and_mahalanobis_sq(v_u, mu, sigma + s_u)
    omega_r, gamma_r = (prior.rot_mean, prior.rot_cov) if reweight_rotation_at == "prior" else (omega_f, gamma_f)
    log_lik_w, rot_maha = gaussian_log_prob_and_mahalanobis_sq(w_u, omega_r, gamma_r + g_u)
    post_lw = prior_lw + log_lik_v + log_lik_w
    post_lw = torch.where(torch.isnan(post_lw), torch.full_like(post_lw, -math.inf), post_lw)
    no_support = ~torch.isfinite(post_lw).any(-1, keepdim=True)
    post_lw = torch.where(no_support, prior_lw, post_lw)  # every class -inf: keep the prior
    post_lw = _normalize_log_weights(post_lw)

    return prior, FactorizedTwistMixture(
        log_weights=post_lw,
        trans_mean=mu_f,
        trans_cov=sigma_f,
        rot_mean=omega_post,
        rot_cov=gamma_post,
        prior_log_weights=prior_lw,
        trans_mahalanobis_sq=trans_maha,
        rot_mahalanobis_sq=rot_maha,
        trans_class_mahalanobis_sq=mahalanobis_sq(v_u, mu, sigma + missing_v),
        rot_class_mahalanobis_sq=mahalanobis_sq(w_u, omega_r, gamma_r + missing_w),
        observed=observed,
    )


def _missing_axes_covariance(cov: torch.Tensor, observed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``cov (B, 3, 3)`` restricted to the ``observed (B, 3)`` axes, plus ``MAX_VARIANCE`` on the others.

    Returns ``(cov', missing)`` with ``missing = diag(MAX_VARIANCE on unobserved axes)``, the term
    that turns a Mahalanobis distance into that of the observed axes' marginal.
    """
    keep = (observed[:, :, None] & observed[:, None, :]).to(cov.dtype)
    missing = torch.diag_embed((~observed).to(cov.dtype) * MAX_VARIANCE)
    return cov * keep + missing, missing


# --------------------------------------------------------------------------- mode search


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
    return whiten, m.log_weights - 3.0 * _LOG_2PI - log_det


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


# --------------------------------------------------------------------------- entropy


def mixture_entropy_bounds(
    log_weights: torch.Tensor, means: torch.Tensor, covs: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds ``(B,), (B,)`` (nats) on the entropy of a Gaussian mixture.

    ``log_weights (B, K)``, ``means (B, K, D)``, ``covs (B, K, D, D)``. Huber et al. 2008:
    upper ``sum_k pi_k (H(N_k) - log pi_k)``; lower
    ``-sum_i pi_i log sum_j pi_j N(m_i; m_j, C_i + C_j)``.
    """
    lw = _normalize_log_weights(log_weights.double())
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


# --------------------------------------------------------------------------- OOD gate


@functools.lru_cache(maxsize=64)
def ood_threshold(alpha: float = 0.85, dof: int = 3) -> float:
    """``chi2.ppf(alpha, dof)``: the gate on the squared Mahalanobis distance (docs/PAPER_DETAILS.md)."""
    from scipy.stats import chi2

    if not 0.0 < alpha < 1.0:
        raise ValueError(f"OOD alpha must be in (0, 1), got {alpha}")
    return float(chi2.ppf(alpha, dof))


OOD_COVARIANCES = ("class", "predictive")
OOD_DOFS = ("translation", "twist")
"""Which blocks of the user command the OOD test looks at (see :func:`is_out_of_distribution`)."""


def is_out_of_distribution(
    fused: FactorizedTwistMixture, alpha: float, covariance: str = "class", dofs: str = "twist"
) -> torch.Tensor:
    """``(B,)`` bool: the user command is farther than ``chi2.ppf(alpha, d)`` (squared Mahalanobis,
    ``d`` the number of observed axes tested) from *every* class, i.e. from the nearest one.

    ``covariance``: ``"class"`` measures the distance under each class's own covariance (docs/PAPER_DETAILS.md:
    "the Mahalanobis distance of the user translation to the nearest class": is the command a
    plausible draw of one of the prior's maneuvers?); ``"predictive"`` adds the user covariance
    (``Sigma_k + S_u``: the density of a noisy command; with the authors' ``S_u`` of 0.01-0.03
    (m/s)^2 it accepts any command within ~0.3 m/s of a class mean, so a prior that has stalled
    keeps control).

    ``dofs``: ``"translation"`` (docs/PAPER_DETAILS.md) tests ``v_u``; ``"twist"`` the sum of the translation
    and rotation distances to the same class (``v_u`` and ``w_u`` are independent given the
    class). Only the observed axes of the command count (``fused.observed``; the marginal
    distance, ``d`` = their number); with none observed the command is never OOD.
    """
    if covariance not in OOD_COVARIANCES:
        raise ValueError(f"covariance must be one of {OOD_COVARIANCES}, got {covariance!r}")
    if dofs not in OOD_DOFS:
        raise ValueError(f"dofs must be one of {OOD_DOFS}, got {dofs!r}")
    if covariance == "class":
        trans, rot = fused.trans_class_mahalanobis_sq, fused.rot_class_mahalanobis_sq
    else:
        trans, rot = fused.trans_mahalanobis_sq, fused.rot_mahalanobis_sq
    if trans is None or rot is None or fused.observed is None:
        raise ValueError("this mixture carries no user command (use fuse_user_command)")
    tested = fused.observed[:, :3].sum(-1)
    maha = trans
    if dofs == "twist":
        tested = tested + fused.observed[:, 3:].sum(-1)
        maha = trans + rot
    thresholds = torch.tensor([math.inf] + [ood_threshold(alpha, d) for d in range(1, 7)], dtype=maha.dtype)
    return maha.min(-1).values > thresholds[tested]


# --------------------------------------------------------------------------- user covariance


class UserCovarianceEstimator:
    """Adaptive user-interface covariances ``S_u`` (translation) and ``G_u`` (rotation), per batch element.

    docs/PAPER_DETAILS.md: start ``diag([0.03]*3 + [0.1]*3)``; keep the last 14 non-zero commands;
    ``S <- 0.8 S + 0.2 sample-cov`` only while ``det^(1/3) > 0.01``. Our reading: the
    translation and rotation blocks are updated separately (the posterior only uses the
    two 3x3 blocks, and ``det^(1/3)`` is the geometric-mean variance of a 3x3 block); the
    sample covariance is over the stored commands (at least ``min_samples``); an update is
    applied only if the *updated* block keeps ``det^(1/3) > floor``, otherwise the block is
    left as it is. So the covariance follows the user's command spread but never
    collapses below a geometric-mean variance of ``floor`` (which would hand the user
    full authority), and it can grow again when the user becomes noisier.
    """

    def __init__(
        self,
        batch_size: int = 1,
        init_trans_var: float = 0.03,
        init_rot_var: float = 0.1,
        window: int = 14,
        decay: float = 0.8,
        floor: float = 0.01,
        min_samples: int = 2,
        adapt: bool = True,
    ) -> None:
        if batch_size < 1 or window < 2 or not 0.0 <= decay <= 1.0 or min_samples < 2 or min_samples > window:
            raise ValueError(
                f"bad UserCovarianceEstimator settings: batch_size={batch_size}, window={window}, "
                f"decay={decay}, min_samples={min_samples}"
            )
        if init_trans_var <= 0 or init_rot_var <= 0 or floor <= 0:
            raise ValueError("initial variances and floor must be positive")
        self.batch_size = batch_size
        self.init_trans_var = init_trans_var
        self.init_rot_var = init_rot_var
        self.window = window
        self.decay = decay
        self.floor = floor
        self.min_samples = min_samples
        self.adapt = adapt
        self.reset()

    def reset(self) -> None:
        """Back to the initial diagonal covariances and an empty command buffer."""
        b = self.batch_size
        eye = torch.eye(3, dtype=torch.float64)
        self.trans_cov = (self.init_trans_var * eye).expand(b, 3, 3).clone()
        """``(B, 3, 3)`` S_u."""
        self.rot_cov = (self.init_rot_var * eye).expand(b, 3, 3).clone()
        """``(B, 3, 3)`` G_u."""
        self._buffer = torch.zeros(b, self.window, 6, dtype=torch.float64)
        self._count = torch.zeros(b, dtype=torch.long)

    @property
    def num_samples(self) -> torch.Tensor:
        """``(B,)`` commands currently stored."""
        return self._count.clamp(max=self.window)

    def update(self, user_twist: torch.Tensor, active: torch.Tensor) -> None:
        """Store the command ``(B, 6)`` of every element with ``active (B,)`` True and adapt."""
        if user_twist.shape != (self.batch_size, 6) or active.shape != (self.batch_size,):
            raise ValueError(
                f"expected user_twist ({self.batch_size}, 6) and active ({self.batch_size},), "
                f"got {tuple(user_twist.shape)} and {tuple(active.shape)}"
            )
        for i in torch.nonzero(active).flatten().tolist():
            self._buffer[i, self._count[i] % self.window] = user_twist[i].double()
            self._count[i] += 1
            n = int(min(self._count[i], self.window))
            if not self.adapt or n < self.min_samples:
                continue
            samples = self._buffer[i, :n]
            centred = samples - samples.mean(0, keepdim=True)
            sample_cov = centred.T @ centred / (n - 1)
            for attr, block in (("trans_cov", slice(0, 3)), ("rot_cov", slice(3, 6))):
                current = getattr(self, attr)
                candidate = self.decay * current[i] + (1.0 - self.decay) * sample_cov[block, block]
                candidate = 0.5 * (candidate + candidate.T)
                det = torch.linalg.det(candidate)
                if det > 0 and float(det) ** (1.0 / 3.0) > self.floor:
                    current[i] = candidate
