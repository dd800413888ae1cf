"""Posterior decision making: fuse a user command with the prior's step-0 twist mixture.

Paper, Sec. "Posterior Decision Making". Per maneuver class ``k`` (B batch, K classes):

* translation (Eq. K_v):   ``kalman_gain = Sigma_k (Sigma_k + S_u)^-1``,
  ``mu_k' = mu_k + K (v_u - mu_k)``, ``Sigma_k' = (I - K) Sigma_k``;
* rotation, conditioned on the fused translation (Eq. K_w): ``(omega_k, Gamma_k) =
  rotation_given_translation(mu_k')``, then the same update with ``w_u`` and ``G_u``;
* class weights (Eq. p(z | h_0, a_0^u)):
  ``pi_k' ∝ pi_k N(v_u; mu_k, Sigma_k + S_u) N(w_u; omega_k, Gamma_k + G_u)``.

The class weights use the *prior* component, as the paper writes the class likelihood
(``N(v_u; mu_z, Sigma_z) N(w_u; omega_z, Gamma_z)``, the rotation Gaussian at the prior translation
mean ``mu_k``), with the user covariance added to both terms: the exact marginal
``∫ N(u; a, S_u) N(a; mu, Sigma) da`` under the paper's likelihood model
``p(u | a) = N(u; a, Sigma_sys)``.

All computation runs in float64; inputs may be float32. Covariances are regularised
(:func:`~rtv3_maniskill.shared_control.gaussians.regularize_covariance`) before use, so no step
can produce NaN from a near-singular network output. The mode of the fused mixture (the executed
action) is :mod:`~rtv3_maniskill.shared_control.mode_search`, the OOD gate on the command
:mod:`~rtv3_maniskill.shared_control.ood_gate`, the user covariances ``S_u``, ``G_u``
:mod:`~rtv3_maniskill.shared_control.user_covariance`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from rtv3_maniskill.shared_control.gaussians import (
    MAX_VARIANCE,
    gaussian_log_prob_and_mahalanobis_sq,
    kalman_update,
    mahalanobis_sq,
    normalize_log_weights,
    regularize_covariance,
)
from rtv3_maniskill.twist_mixture import TwistMixture


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


def _prior_translation(mixture: TwistMixture) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Normalised class log-weights ``(B, K)``, translation means and regularised covariances (float64)."""
    _check_mixture(mixture)
    lw = normalize_log_weights(mixture.log_weights.double())
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
    observed: torch.Tensor | None = None,
) -> FactorizedTwistMixture:
    """Posterior step-0 mixture given the user command (paper, Sec. Posterior Decision Making).

    Args:
        mixture: the prior's step-0 mixture, B batch, K classes.
        user_twist: ``(B, 6)`` user command ``[v_u, w_u]``, EE body frame.
        user_trans_cov: ``(B, 3, 3)`` ``S_u`` (the paper's Sigma^sys).
        user_rot_cov: ``(B, 3, 3)`` ``G_u`` (the paper's Gamma^sys).
        observed: optional ``(B, 6)`` bool, the axes of the command that carry an observation
            (default: all). An unobserved axis is a missing measurement, not a zero one: the
            user covariance gets an infinite variance (``MAX_VARIANCE``) along it and no
            correlation with the other axes, so the Kalman gain, the class likelihood and the
            OOD distances ignore it (exactly, up to ``1 / MAX_VARIANCE``).
    Returns:
        The fused mixture; ``log_weights`` are ``log pi_k'``.
    """
    return prior_and_fused_mixtures(mixture, user_twist, user_trans_cov, user_rot_cov, observed)[1]


def prior_and_fused_mixtures(
    mixture: TwistMixture,
    user_twist: torch.Tensor,
    user_trans_cov: torch.Tensor,
    user_rot_cov: torch.Tensor,
    observed: torch.Tensor | None = None,
) -> tuple[FactorizedTwistMixture, FactorizedTwistMixture]:
    """``(prior_twist_mixture(mixture), fuse_user_command(mixture, ...))`` with the rotation Gaussians
    at the prior means ``mu_k`` and at the fused means ``mu_k'`` from one call of
    ``rotation_given_translation`` (one pass through the network's rotation head per step).
    Arguments as :func:`fuse_user_command`."""
    prior_lw, mu, sigma = _prior_translation(mixture)
    b, k = prior_lw.shape
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
    # in the same call.
    omega, gamma = _rotation_at(mixture, torch.stack([mu, mu_f]))
    prior = FactorizedTwistMixture(prior_lw, mu, sigma, omega[0], gamma[0], prior_lw.clone())
    omega_f, gamma_f = omega[1], gamma[1]
    # ... then fused with w_u (Eq. K_w).
    omega_post, gamma_post = kalman_update(omega_f, gamma_f, w_u, g_u)[:2]

    # Class re-weighting (Eq. p(z | h_0, a_0^u)) with the prior components, in log space.
    # Sums of two regularised SPD matrices are SPD: no second eigen-decomposition needed.
    log_lik_v, trans_maha = gaussian_log_prob_and_mahalanobis_sq(v_u, mu, sigma + s_u)
    log_lik_w, rot_maha = gaussian_log_prob_and_mahalanobis_sq(w_u, prior.rot_mean, prior.rot_cov + g_u)
    post_lw = prior_lw + log_lik_v + log_lik_w
    post_lw = torch.where(torch.isnan(post_lw), torch.full_like(post_lw, -math.inf), post_lw)
    no_support = ~torch.isfinite(post_lw).any(-1, keepdim=True)
    post_lw = torch.where(no_support, prior_lw, post_lw)  # every class -inf: keep the prior
    post_lw = normalize_log_weights(post_lw)

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
        rot_class_mahalanobis_sq=mahalanobis_sq(w_u, prior.rot_mean, prior.rot_cov + missing_w),
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
