"""Posterior decision making (paper Sec. "Posterior Decision Making") and the shared controller."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2, multivariate_normal

from rtv3_maniskill import features
from rtv3_maniskill.shared_control import gaussians, mixture_entropy, mode_search, ood_gate, posterior, user_covariance
from rtv3_maniskill.shared_control.autonomy import surface_distance
from rtv3_maniskill.shared_control.command_axes import observed_axes
from rtv3_maniskill.shared_control.config import SharedControlConfig
from rtv3_maniskill.shared_control.shared_controller import SharedController
from rtv3_maniskill.shared_control.twist_utils import clamp_twist_speed
from rtv3_maniskill.twist_mixture import TwistMixture

DT = torch.float64


def random_spd(gen: torch.Generator, *shape: int, scale: float = 0.1) -> torch.Tensor:
    a = torch.randn(*shape, 3, 3, generator=gen, dtype=DT) * scale
    return a @ a.transpose(-1, -2) + 0.01 * torch.eye(3, dtype=DT)


def linear_rotation(weight: torch.Tensor, bias: torch.Tensor, cov: torch.Tensor):
    """omega_k(v) = W_k v + b_k, Gamma_k constant: a hand-built translation-conditioned rotation."""

    def fn(v: torch.Tensor):
        omega = torch.einsum("kij,...kj->...ki", weight.to(v.dtype), v) + bias.to(v.dtype)
        return omega, cov.to(v.dtype).expand(*v.shape[:-1], 3, 3)

    return fn


# --------------------------------------------------------------------------- Kalman fusion


def test_kalman_update_equals_information_form_product():
    gen = torch.Generator().manual_seed(0)
    mean = torch.randn(5, 3, generator=gen, dtype=DT) * 0.1
    cov = random_spd(gen, 5)
    obs = torch.randn(5, 3, generator=gen, dtype=DT) * 0.1
    obs_cov = random_spd(gen, 5)
    new_mean, new_cov, gain = gaussians.kalman_update(mean, cov, obs, obs_cov)
    info = torch.linalg.inv(cov) + torch.linalg.inv(obs_cov)
    expected_cov = torch.linalg.inv(info)
    expected_mean = (expected_cov @ (torch.linalg.solve(cov, mean[..., None])
                                     + torch.linalg.solve(obs_cov, obs[..., None])))[..., 0]
    torch.testing.assert_close(new_cov, expected_cov, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(new_mean, expected_mean, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(gain, cov @ torch.linalg.inv(cov + obs_cov))


def test_fused_gaussian_is_the_normalised_product_of_prior_and_likelihood():
    """log N(x; mu, S) + log N(v_u; x, S_u) - log N(x; mu', S') is constant in x and equals
    log N(v_u; mu, S + S_u): the fusion and the class-weight marginal agree (brute force)."""
    rng = np.random.default_rng(1)
    mu, v_u = rng.normal(0, 0.1, 3), rng.normal(0, 0.1, 3)
    a, b = rng.normal(0, 0.2, (3, 3)), rng.normal(0, 0.2, (3, 3))
    sigma, s_u = a @ a.T + 0.01 * np.eye(3), b @ b.T + 0.01 * np.eye(3)
    new_mean, new_cov, _ = gaussians.kalman_update(*(torch.tensor(x) for x in (mu, sigma, v_u, s_u)))
    xs = rng.normal(0, 0.3, (50, 3))
    log_ratio = (
        multivariate_normal(mu, sigma).logpdf(xs)
        + multivariate_normal(v_u, s_u).logpdf(xs)  # N(v_u; x, S_u) = N(x; v_u, S_u)
        - multivariate_normal(new_mean.numpy(), new_cov.numpy()).logpdf(xs)
    )
    assert np.ptp(log_ratio) < 1e-8
    assert log_ratio[0] == pytest.approx(multivariate_normal(mu, sigma + s_u).logpdf(v_u), abs=1e-8)


def make_two_class_mixture(weights=(0.5, 0.5), batch: int = 1, dtype=torch.float32) -> TwistMixture:
    """Class 0 moves along -x and rolls -z, class 1 along +x and rolls +z (rotation depends on v)."""
    mu = torch.tensor([[-0.3, 0.0, 0.0], [0.3, 0.0, 0.0]], dtype=dtype)
    cov = torch.diag_embed(torch.tensor([[0.002, 0.002, 0.002], [0.002, 0.002, 0.002]], dtype=dtype))
    weight = torch.zeros(2, 3, 3)
    weight[:, 2, 0] = 2.0  # omega_z = 2 v_x
    rot = linear_rotation(weight, torch.zeros(2, 3), 0.01 * torch.eye(3))
    lw = torch.log(torch.tensor(weights, dtype=dtype))
    return TwistMixture(lw.expand(batch, 2).clone(), mu.expand(batch, 2, 3).clone(), cov.expand(batch, 2, 3, 3).clone(),
                        rot)


def user_covs(batch: int = 1, trans: float = 0.03, rot: float = 0.1):
    eye = torch.eye(3, dtype=DT)
    return (trans * eye).expand(batch, 3, 3), (rot * eye).expand(batch, 3, 3)


def test_fuse_user_command_per_class_translation_then_conditioned_rotation():
    gen = torch.Generator().manual_seed(2)
    b, k = 2, 4
    mu = torch.randn(b, k, 3, generator=gen, dtype=DT) * 0.1
    sigma = random_spd(gen, b, k)
    weight = torch.randn(k, 3, 3, generator=gen, dtype=DT)
    bias = torch.randn(k, 3, generator=gen, dtype=DT) * 0.1
    gamma = random_spd(gen, k)[None]
    rot = linear_rotation(weight, bias, gamma)
    mixture = TwistMixture(torch.log_softmax(torch.randn(b, k, generator=gen, dtype=DT), -1), mu, sigma, rot)
    user = torch.randn(b, 6, generator=gen, dtype=DT) * 0.1
    s_u, g_u = random_spd(gen, b), random_spd(gen, b)
    fused = posterior.fuse_user_command(mixture, user, s_u, g_u)
    exp_mu, exp_sigma, _ = gaussians.kalman_update(mu, sigma, user[:, None, :3].expand(b, k, 3), s_u[:, None])
    torch.testing.assert_close(fused.trans_mean, exp_mu)
    torch.testing.assert_close(fused.trans_cov, exp_sigma)
    omega_at_fused, gamma_at_fused = rot(exp_mu)
    exp_omega, exp_gamma, _ = gaussians.kalman_update(omega_at_fused, gamma_at_fused, user[:, None, 3:].expand(b, k, 3),
                                                      g_u[:, None])
    torch.testing.assert_close(fused.rot_mean, exp_omega)
    torch.testing.assert_close(fused.rot_cov, exp_gamma)


def test_prior_and_fused_in_one_call_equal_the_separate_functions():
    # The controller gets both mixtures from one rotation-head call; it must give exactly what
    # prior_twist_mixture and fuse_user_command give.
    gen = torch.Generator().manual_seed(5)
    b, k = 3, 4
    rot = linear_rotation(torch.randn(k, 3, 3, generator=gen, dtype=DT),
                          torch.randn(k, 3, generator=gen, dtype=DT) * 0.1, random_spd(gen, k)[None])
    mixture = TwistMixture(torch.log_softmax(torch.randn(b, k, generator=gen, dtype=DT), -1),
                           torch.randn(b, k, 3, generator=gen, dtype=DT) * 0.1, random_spd(gen, b, k), rot)
    user = torch.randn(b, 6, generator=gen, dtype=DT) * 0.1
    s_u, g_u = random_spd(gen, b), random_spd(gen, b)
    observed = torch.rand(b, 6, generator=gen) > 0.3
    prior, fused = posterior.prior_and_fused_mixtures(mixture, user, s_u, g_u, observed=observed)
    expected_prior = posterior.prior_twist_mixture(mixture)
    expected = posterior.fuse_user_command(mixture, user, s_u, g_u, observed=observed)
    for name in ("log_weights", "trans_mean", "trans_cov", "rot_mean", "rot_cov", "trans_mahalanobis_sq",
                 "rot_mahalanobis_sq", "trans_class_mahalanobis_sq", "rot_class_mahalanobis_sq"):
        torch.testing.assert_close(getattr(fused, name), getattr(expected, name), msg=name)
    for name in ("log_weights", "trans_mean", "trans_cov", "rot_mean", "rot_cov"):
        torch.testing.assert_close(getattr(prior, name), getattr(expected_prior, name), msg=name)


def test_class_weights_match_closed_form():
    """The class likelihood takes the rotation Gaussian at the prior translation mean ``mu_k``."""
    mixture = make_two_class_mixture(weights=(0.3, 0.7), dtype=DT)
    user = torch.tensor([[0.05, 0.02, -0.01, 0.1, 0.0, 0.05]], dtype=DT)
    s_u, g_u = user_covs()
    fused = posterior.fuse_user_command(mixture, user, s_u, g_u)
    logs = []
    for k in range(2):
        mu, sigma = mixture.trans_mean[0, k].numpy(), mixture.trans_cov[0, k].numpy()
        omega, gamma = mixture.rotation_given_translation(mixture.trans_mean)
        logs.append(
            math.log(mixture.weights[0, k])
            + multivariate_normal(mu, sigma + s_u[0].numpy()).logpdf(user[0, :3].numpy())
            + multivariate_normal(omega[0, k].numpy(), gamma[0, k].numpy() + g_u[0].numpy()).logpdf(user[0, 3:].numpy())
        )
    expected = np.exp(np.array(logs) - np.logaddexp(*logs))
    np.testing.assert_allclose(fused.weights[0].numpy(), expected, rtol=1e-9)


def test_user_command_near_a_class_raises_its_weight():
    mixture = make_two_class_mixture()
    s_u, g_u = user_covs()
    toward_1 = torch.tensor([[0.27, 0.0, 0.0, 0.0, 0.0, 0.54]])
    fused = posterior.fuse_user_command(mixture, toward_1, s_u, g_u)
    assert fused.weights[0, 1] > 0.99
    # fused translation of class 1 lies between the user command and the prior mean
    assert 0.27 < fused.trans_mean[0, 1, 0] < 0.3
    # the closer the command, the higher the weight
    weaker = posterior.fuse_user_command(mixture, torch.tensor([[0.05, 0.0, 0.0, 0.0, 0.0, 0.0]]), s_u, g_u)
    assert 0.5 < weaker.weights[0, 1] < fused.weights[0, 1]
    toward_0 = -toward_1
    assert posterior.fuse_user_command(mixture, toward_0, s_u, g_u).weights[0, 0] > 0.9


def test_posterior_is_finite_for_degenerate_inputs():
    mixture = make_two_class_mixture()
    mixture.trans_cov = torch.zeros_like(mixture.trans_cov)  # singular network output
    s_u, g_u = user_covs()
    far = torch.tensor([[50.0, -50.0, 50.0, 30.0, 30.0, -30.0]])
    fused = posterior.fuse_user_command(mixture, far, s_u, g_u)
    for t in (fused.log_weights, fused.trans_mean, fused.trans_cov, fused.rot_mean, fused.rot_cov):
        assert torch.isfinite(t).all()
    assert torch.isfinite(mode_search.mixture_mode(fused)).all()
    assert fused.weights.sum() == pytest.approx(1.0)


def test_posterior_rejects_bad_inputs():
    mixture = make_two_class_mixture()
    s_u, g_u = user_covs()
    with pytest.raises(ValueError, match="user_twist"):
        posterior.fuse_user_command(mixture, torch.zeros(1, 5), s_u, g_u)
    with pytest.raises(ValueError, match="NaN"):
        posterior.fuse_user_command(mixture, torch.full((1, 6), math.nan), s_u, g_u)
    bad = make_two_class_mixture()
    bad.trans_mean[0, 0, 0] = math.nan
    with pytest.raises(ValueError, match="trans_mean"):
        posterior.fuse_user_command(bad, torch.zeros(1, 6), s_u, g_u)


# --------------------------------------------------------------------------- mode, entropy


def _factorized(weights, means, trans_var, rot_var) -> posterior.FactorizedTwistMixture:
    k = len(weights)
    lw = torch.log(torch.tensor([weights], dtype=DT))
    means = torch.tensor([means], dtype=DT)
    t_cov = torch.diag_embed(torch.tensor([[[v] * 3 for v in trans_var]], dtype=DT))
    r_cov = torch.diag_embed(torch.tensor([[[v] * 3 for v in rot_var]], dtype=DT))
    assert means.shape == (1, k, 6)
    return posterior.FactorizedTwistMixture(lw, means[..., :3], t_cov, means[..., 3:], r_cov, lw)


def test_mode_of_single_gaussian_is_its_mean():
    m = _factorized([1.0], [[0.1, -0.2, 0.3, 0.4, 0.0, -0.1]], [0.01], [0.02])
    torch.testing.assert_close(mode_search.mixture_mode(m)[0], m.means[0, 0])


def test_mode_between_overlapping_components_beats_every_component_mean():
    # Two equal, strongly overlapping classes: the mode is midway, not at either mean.
    m = _factorized([0.5, 0.5], [[-0.05, 0, 0, 0, 0, 0], [0.05, 0, 0, 0, 0, 0]], [0.01, 0.01], [0.01, 0.01])
    mode = mode_search.mixture_mode(m)
    assert mode[0].abs().max() < 1e-4
    dens_mode = mode_search.mixture_log_density(mode[:, None], m)
    dens_means = mode_search.mixture_log_density(m.means, m)
    assert (dens_mode > dens_means + 1e-4).all()


def test_mode_is_at_least_as_dense_as_random_samples():
    gen = torch.Generator().manual_seed(3)
    k = 5
    m = posterior.FactorizedTwistMixture(
        torch.log_softmax(torch.randn(1, k, generator=gen, dtype=DT), -1),
        torch.randn(1, k, 3, generator=gen, dtype=DT) * 0.1,
        random_spd(gen, 1, k, scale=0.05),
        torch.randn(1, k, 3, generator=gen, dtype=DT) * 0.2,
        random_spd(gen, 1, k, scale=0.1),
        torch.zeros(1, k, dtype=DT),
    )
    samples = (m.means[:, torch.randint(0, k, (4000,), generator=gen)]
               + 0.05 * torch.randn(1, 4000, 6, generator=gen, dtype=DT))
    best_sample = mode_search.mixture_log_density(samples, m).max()
    assert mode_search.mixture_log_density(mode_search.mixture_mode(m)[:, None], m)[0, 0] >= best_sample


def test_mode_search_stopping_early_finds_the_same_mode():
    # Two overlapping classes: the mode is not a component mean, so the iteration does the work.
    m = _factorized([0.6, 0.4], [[-0.05, 0.02, 0, 0.1, 0, 0], [0.05, 0, 0, 0, 0.1, 0]], [0.01, 0.02], [0.01, 0.03])
    full = mode_search.mixture_mode(m, num_iters=200, tol=0.0)
    torch.testing.assert_close(mode_search.mixture_mode(m, tol=1e-6), full, atol=1e-5, rtol=0)
    assert not torch.allclose(mode_search.mixture_mode(m, num_iters=0), full, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="tol"):
        mode_search.mixture_mode(m, tol=float("nan"))


def test_entropy_bounds_bracket_monte_carlo_entropy():
    gen = torch.Generator().manual_seed(4)
    k = 3
    lw = torch.log(torch.tensor([[0.2, 0.5, 0.3]], dtype=DT))
    means = torch.randn(1, k, 3, generator=gen, dtype=DT) * 0.1
    covs = random_spd(gen, 1, k, scale=0.05)
    lower, upper = mixture_entropy.mixture_entropy_bounds(lw, means, covs)
    comp = torch.multinomial(lw.exp()[0], 20000, replacement=True, generator=gen)
    chol = torch.linalg.cholesky(covs[0])
    x = means[0, comp] + (chol[comp] @ torch.randn(20000, 3, 1, generator=gen, dtype=DT))[..., 0]
    logp = torch.logsumexp(lw[0] + gaussians.gaussian_log_prob(x[:, None], means[0], covs[0]), -1)
    mc = -logp.mean()
    assert lower[0] - 0.02 <= mc <= upper[0] + 0.02
    assert lower[0] < upper[0]
    # single Gaussian: the upper bound is its exact entropy
    _, up1 = mixture_entropy.mixture_entropy_bounds(torch.zeros(1, 1, dtype=DT), means[:, :1], covs[:, :1])
    assert up1[0] == pytest.approx(float(gaussians.gaussian_entropy(covs[0, 0])))


# --------------------------------------------------------------------------- user covariance, OOD


def test_ood_threshold_is_chi2_quantile_on_squared_mahalanobis():
    assert ood_gate.ood_threshold(0.85) == pytest.approx(chi2.ppf(0.85, 3))
    assert ood_gate.ood_threshold(0.85, 6) == pytest.approx(chi2.ppf(0.85, 6))
    mixture = make_two_class_mixture()
    s_u, g_u = user_covs()
    near = posterior.fuse_user_command(mixture, torch.tensor([[0.3, 0, 0, 0, 0, 0.6]]), s_u, g_u)
    far = posterior.fuse_user_command(mixture, torch.tensor([[0.0, 0.0, 0.6, 0, 0, 0]]), s_u, g_u)
    for covariance in ood_gate.OOD_COVARIANCES:
        assert not ood_gate.is_out_of_distribution(near, 0.85, covariance)[0]
        assert ood_gate.is_out_of_distribution(far, 0.85, covariance)[0]
    # (0.3^2 + 0.6^2) to the nearest class, under Sigma_k + S_u = 0.032 I and Sigma_k = 0.002 I
    assert far.trans_mahalanobis_sq.min() == pytest.approx((0.09 + 0.36) / 0.032, rel=1e-4)
    assert far.trans_class_mahalanobis_sq.min() == pytest.approx((0.09 + 0.36) / 0.002, rel=1e-4)


def test_ood_gate_covariance_class_rejects_what_only_the_user_noise_would_explain():
    """0.15 m/s off class 1's mean, rotation on it: 3.4 sigma of the class (OOD), 0.8 sigma of class + user noise."""
    mixture = make_two_class_mixture()
    s_u, g_u = user_covs()
    fused = posterior.fuse_user_command(mixture, torch.tensor([[0.3, 0.15, 0, 0, 0, 0.6]]), s_u, g_u)
    assert ood_gate.is_out_of_distribution(fused, 0.85, "class")[0]
    assert not ood_gate.is_out_of_distribution(fused, 0.85, "predictive")[0]
    with pytest.raises(ValueError, match="covariance must be one of"):
        ood_gate.is_out_of_distribution(fused, 0.85, "joint")


def test_ood_gate_tests_the_observed_axes_of_the_command():
    mixture = make_two_class_mixture()  # class 1: v = (0.3, 0, 0), omega_z = 2 v_x = 0.6, Gamma = 0.01 I
    s_u, g_u = user_covs()

    def ood(command, missing_zeros=True):
        command = torch.tensor([command])
        observed = command.abs() > 0 if missing_zeros else None
        fused = posterior.fuse_user_command(mixture, command, s_u, g_u, observed=observed)
        return bool(ood_gate.is_out_of_distribution(fused, 0.85, "class")[0])

    # translation only, matching class 1: its zero rotation is missing, not a command to hold still
    translation_only = [0.3, 0, 0, 0, 0, 0]
    assert not ood(translation_only)
    assert ood(translation_only, missing_zeros=False)  # 0.6^2 / 0.01 = 36 > chi2(0.85, 6)
    # rotation only, opposite to every class's rotation
    assert ood([0, 0, 0, 0, 0, -1.0])
    # one axis tested against chi2(0.85, 1) = 2.07: 0.15 m/s off class 1's v_x (3.4 sigma) is OOD, 0.03 is not
    assert ood([0.45, 0, 0, 0, 0, 0]) and not ood([0.33, 0, 0, 0, 0, 0])
    # a full twist matching class 1 passes; nothing observed is never OOD
    assert not ood([0.3, 0, 0, 0, 0, 0.6])
    assert not ood([0.0] * 6)


def test_missing_axes_are_left_to_the_prior_and_equal_a_huge_user_variance():
    mixture = make_two_class_mixture(weights=(0.5, 0.5))
    s_u, g_u = user_covs()
    command = torch.tensor([[0.25, 0.0, 0.0, 0.0, 0.0, 0.0]])  # only v_x given
    fused = posterior.fuse_user_command(mixture, command, s_u, g_u, observed=command.abs() > 0)
    # unobserved axes: the classes' own values (v_y = v_z = 0, omega_z = 2 v_x at the fused v_x)
    torch.testing.assert_close(fused.trans_mean[0, :, 1:], torch.zeros(2, 2, dtype=DT), atol=1e-6, rtol=0)
    torch.testing.assert_close(fused.rot_mean[0, :, 2], 2 * fused.trans_mean[0, :, 0], atol=1e-5, rtol=0)
    # the observed axis is fused as a 1-D Kalman update: 0.3 + 0.002 / 0.032 * (0.25 - 0.3)
    assert float(fused.trans_mean[0, 1, 0]) == pytest.approx(0.3 - 0.05 * 0.002 / 0.032, rel=1e-6)
    # class weights: only v_x's likelihood counts, which favours class 1 (+x)
    assert fused.weights[0, 1] > 0.99
    # same as a user covariance with a huge variance on the missing axes
    big = torch.diag(torch.tensor([0.03, 1e6, 1e6], dtype=DT))[None]
    reference = posterior.fuse_user_command(mixture, command, big, (1e6 * torch.eye(3, dtype=DT))[None])
    torch.testing.assert_close(fused.trans_mean, reference.trans_mean)
    torch.testing.assert_close(fused.log_weights, reference.log_weights)
    with pytest.raises(ValueError, match="observed must be"):
        posterior.fuse_user_command(mixture, command, s_u, g_u, observed=torch.ones(1, 3, dtype=torch.bool))


def test_shared_control_config_rejects_unknown_ood_gate_options():
    with pytest.raises(ValueError, match="ood_covariance must be one of"):
        SharedControlConfig(ood_covariance="user")
    with pytest.raises(ValueError, match="uncommanded_axes must be one of"):
        SharedControlConfig(uncommanded_axes="zero")


def test_user_covariance_follows_command_spread_but_not_below_floor():
    est = user_covariance.UserCovarianceEstimator(batch_size=2)
    torch.testing.assert_close(est.trans_cov[0], 0.03 * torch.eye(3, dtype=DT))
    torch.testing.assert_close(est.rot_cov[1], 0.1 * torch.eye(3, dtype=DT))
    rng = np.random.default_rng(5)
    for _ in range(60):
        noisy = torch.from_numpy(rng.normal(0.0, math.sqrt(0.05), 6))
        steady = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.1], dtype=DT)
        est.update(torch.stack([noisy, steady]), torch.tensor([True, True]))
    # element 0 (noisy commands, variance 0.05): S_u moved from 0.03 towards 0.05
    assert 0.035 < torch.diagonal(est.trans_cov[0]).mean() < 0.07
    # element 1 (identical commands): shrinks, but det^(1/3) stays above the 0.01 floor
    for cov in (est.trans_cov[1], est.rot_cov[1]):
        geo = float(torch.linalg.det(cov)) ** (1 / 3)
        assert 0.01 < geo < 0.0126
    assert est.num_samples.tolist() == [14, 14]
    est.update(torch.ones(2, 6, dtype=DT), torch.tensor([False, False]))  # inactive: nothing stored
    assert est._count.tolist() == [60, 60]
    est.reset()
    torch.testing.assert_close(est.trans_cov[1], 0.03 * torch.eye(3, dtype=DT))


def test_user_covariance_of_a_batch_equals_each_element_alone():
    # Elements command at different times (some steps inactive) and with different spreads; the
    # batched update must give every element exactly what it would get on its own.
    rng = np.random.default_rng(11)
    b, steps = 4, 40
    commands = torch.from_numpy(rng.normal(0.0, 1.0, (steps, b, 6)) * np.array([0.3, 0.05, 0.01, 0.02])[:, None])
    active = torch.from_numpy(rng.random((steps, b)) < np.array([1.0, 0.7, 0.4, 0.1]))
    batched = user_covariance.UserCovarianceEstimator(batch_size=b)
    alone = [user_covariance.UserCovarianceEstimator(batch_size=1) for _ in range(b)]
    for t in range(steps):
        batched.update(commands[t], active[t])
        for i in range(b):
            alone[i].update(commands[t, i : i + 1], active[t, i : i + 1])
    for i in range(b):
        torch.testing.assert_close(batched.trans_cov[i], alone[i].trans_cov[0], rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(batched.rot_cov[i], alone[i].rot_cov[0], rtol=1e-12, atol=1e-14)
        assert int(batched.num_samples[i]) == int(alone[i].num_samples[0])
    # the spreads differ, so the elements' covariances do too (the test is not vacuous)
    assert not torch.allclose(batched.trans_cov[0], batched.trans_cov[2])


# --------------------------------------------------------------------------- shared controller


class HandBuiltPrior:
    """Test double of the learned network: a fixed two-class step-0 mixture."""

    def __init__(self, weights=(0.3, 0.7)):
        self.weights = weights
        self.mixture_calls = 0
        self.resets = 0

    def predict_step0_mixture(self, observation):
        self.mixture_calls += 1
        state = observation[features.STATE]
        return make_two_class_mixture(self.weights, batch=1 if state.ndim == 1 else state.shape[0])

    def reset(self):
        self.resets += 1


def make_observation(ee=(0.0, 0.0, 0.3), cloud_points=((0.0, 0.0, 0.0),), batch: int = 1, grasps: int = 3):
    """A batched feature dict (every element the same)."""
    state = torch.zeros(features.STATE_DIM)
    state[features.EE_POS] = torch.tensor(ee)
    state[features.EE_QUAT] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    cloud = torch.zeros(8, 6)
    mask = torch.zeros(8)
    for i, p in enumerate(cloud_points):
        cloud[i, :3] = torch.tensor(p)
        mask[i] = 1.0
    gmask = torch.zeros(4)
    gmask[:grasps] = 1.0
    obs = {
        features.STATE: state,
        features.POINT_CLOUD: cloud,
        features.POINT_CLOUD_MASK: mask,
        features.GRASPS: torch.zeros(4, features.GRASP_DIM).index_fill(1, torch.tensor([3]), 1.0),  # identity quat
        features.GRASPS_MASK: gmask,
    }
    return {k: v.expand(batch, *v.shape).clone() for k, v in obs.items()}


def test_no_input_far_from_objects_runs_the_prior_autonomously():
    prior = HandBuiltPrior()
    ctrl = SharedController(prior, SharedControlConfig(autonomy_cutoff_distance=0.07))
    for user in (None, torch.zeros(1, 6)):
        action = ctrl.step(make_observation(ee=(0, 0, 0.3)), user)
        assert ctrl.last_diagnostics.mode == "autonomous"
        torch.testing.assert_close(action, torch.tensor([[0.3, 0.0, 0.0, 0.0, 0.0, 0.6]]))
    assert action.shape == (1, 6) and action.dtype == torch.float32
    # class weights shown are the prior's
    torch.testing.assert_close(ctrl.last_diagnostics.class_weights[0].float(), torch.tensor([0.3, 0.7]))


def test_autonomous_action_is_the_policys_most_likely_action():
    # The controller reads the most likely action off the step-0 mixture it already has; it must
    # equal what the policy's own select_action executes (argmax class, then the Gaussian means).
    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

    torch.manual_seed(0)
    policy = RTV3Policy(RTV3Config(device="cpu", num_points=8, max_grasps=4)).eval()
    gen = torch.Generator().manual_seed(1)
    obs = make_observation(ee=(0.0, 0.0, 0.3), grasps=2)
    obs[features.GRASPS] = torch.cat([torch.rand(4, 3, generator=gen) * 0.1, torch.tensor([[0.0, 1.0, 0.0, 0.0]] * 4),
                                      torch.full((4, 1), 0.04), torch.ones(4, 1)], -1)[None]
    ctrl = SharedController(policy, SharedControlConfig(max_linear_speed=None, max_angular_speed=None))
    ctrl.reset()
    action = ctrl.step(obs, None)
    assert ctrl.last_diagnostics.mode == "autonomous"
    policy.reset()
    expected = policy.select_action(obs).reshape(1, 6)
    torch.testing.assert_close(action, expected, atol=1e-5, rtol=1e-4)


def test_no_input_near_the_object_surface_hands_control_to_the_user():
    prior = HandBuiltPrior()
    ctrl = SharedController(prior, SharedControlConfig(autonomy_cutoff_distance=0.07))
    obs = make_observation(ee=(0.0, 0.0, 0.3), cloud_points=((0.0, 0.0, 0.25), (0.5, 0.5, 0.0)))
    assert surface_distance(obs)[0] == pytest.approx(0.05)
    action = ctrl.step(obs, None)
    assert ctrl.last_diagnostics.mode == "user_only"
    assert torch.equal(action, torch.zeros(1, 6))
    # padded points (mask 0) do not count: the only valid point is far away
    obs[features.POINT_CLOUD_MASK][0, 0] = 0.0
    ctrl.step(obs, None)
    assert ctrl.last_diagnostics.mode == "autonomous"


def test_the_table_top_is_part_of_the_scene_for_the_proximity_rules():
    """The cloud is cropped above the table, so the table top (``table_height``) counts on its own:
    5 cm above it, far from every cloud point, there is no autonomy (``table_height=None``: there is)."""
    obs = make_observation(ee=(0.0, 0.0, 0.05), cloud_points=((0.5, 0.5, 0.0),))
    assert surface_distance(obs)[0] > 0.5
    assert surface_distance(obs, table_height=0.0)[0] == pytest.approx(0.05)
    assert surface_distance(obs, table_height=-0.2)[0] > 0.2  # a table farther than the cloud
    ctrl = SharedController(HandBuiltPrior(), SharedControlConfig())
    ctrl.step(obs, None)
    assert ctrl.last_diagnostics.mode == "user_only"
    ctrl = SharedController(HandBuiltPrior(), SharedControlConfig(table_height=None))
    ctrl.step(obs, None)
    assert ctrl.last_diagnostics.mode == "autonomous"
    with pytest.raises(ValueError, match="table_height"):
        SharedControlConfig(table_height=math.nan)


def test_user_command_gives_shared_control_that_blends_towards_the_matching_class():
    prior = HandBuiltPrior(weights=(0.7, 0.3))
    # the hand-built prior's covariances are taken as they are (the paper's reading)
    ctrl = SharedController(prior, SharedControlConfig(prior_covariance_scale=1.0))
    user = torch.tensor([[0.27, 0.0, 0.0, 0.0, 0.0, 0.0]])
    action = ctrl.step(make_observation(), user)[0]
    d = ctrl.last_diagnostics
    assert d.mode == "shared" and not d.ood[0]
    assert d.class_weights[0, 1] > 0.9 > d.prior_class_weights[0, 1]
    # translation pulled from the user's 0.27 towards class 1's 0.3; the rotation the user does not
    # command follows class 1 (omega_z = 2 v_x)
    assert 0.27 < action[0] < 0.3
    assert action[5] > 0.2
    for name in ("trans_entropy_lower", "trans_entropy_upper", "rot_entropy_lower", "rot_entropy_upper"):
        assert torch.isfinite(getattr(d, name)).all()
    assert d.trans_entropy_lower[0] <= d.trans_entropy_upper[0]


def test_prior_covariance_scale_gives_the_users_command_more_weight():
    """A larger prior_covariance_scale moves the shared action from the prior's class mean towards
    the user's command, by the Kalman gain of the scaled covariance; scale 1 is the plain fusion."""
    user = torch.tensor([[0.2, 0.0, 0.0, 0.0, 0.0, 0.0]])
    actions = {}
    for scale in (1.0, 10.0):
        ctrl = SharedController(HandBuiltPrior(weights=(0.01, 0.99)), SharedControlConfig(
            prior_covariance_scale=scale, user_cov_decay=1.0, max_linear_speed=None, belief_memory=0.0))
        actions[scale] = ctrl.step(make_observation(), user)[0]
        assert ctrl.last_diagnostics.mode == "shared"
    # class 1: mean 0.3, variance 0.002 per axis; user variance 0.03
    for scale, action in actions.items():
        gain = 0.002 * scale / (0.002 * scale + 0.03)
        assert action[0].item() == pytest.approx(0.3 + gain * (0.2 - 0.3), abs=2e-3)
    assert actions[10.0][0] < actions[1.0][0]
    with pytest.raises(ValueError, match="prior_covariance_scale"):
        SharedControlConfig(prior_covariance_scale=0.0)


def test_observed_axes_hold_the_axes_the_user_has_used():
    """``"missing"``: every zero axis is missing. ``"missing_unused"``: far from the scene a used
    axis is held still and an unused one is the prior's; near it, every axis of a used kind is held."""
    t, f = True, False
    commanded = torch.tensor([[t, f, f, f, f, f]])  # pushes along x now
    used = torch.tensor([[t, f, f, t, f, f]])  # has pushed along x and rolled about x before
    far, near = torch.tensor([False]), torch.tensor([True])
    for where in (far, near):
        assert torch.equal(observed_axes("missing", commanded, used, where), commanded)
    assert observed_axes("missing_unused", commanded, used, far).tolist() == [[t, f, f, t, f, f]]
    assert observed_axes("missing_unused", commanded, used, near).tolist() == [[t] * 6]
    translation_only = torch.tensor([[t, f, f, f, f, f]])  # rotation never commanded: the prior's near the scene too
    assert observed_axes("missing_unused", commanded, translation_only, near).tolist() == [[t, t, t, f, f, f]]
    with pytest.raises(ValueError, match="uncommanded_axes must be one of"):
        observed_axes("zero", commanded, used, far)


def test_shared_action_fuses_the_observed_axes_of_the_command():
    """After a roll about x, a push along x alone: the controller's action is the mode of the fusion
    on the axes :func:`observed_axes` gives, so the rotation about z the user has never commanded is
    the prior's far from the scene and held still near it."""
    user = torch.tensor([[0.27, 0.0, 0.0, 0.0, 0.0, 0.0]])
    roll = torch.tensor([[0.27, 0.0, 0.0, 0.3, 0.0, 0.0]])
    far = make_observation(ee=(0.0, 0.0, 0.3), cloud_points=((0.0, 0.0, 0.0),))
    near = make_observation(ee=(0.0, 0.0, 0.3), cloud_points=((0.0, 0.0, 0.25),))
    config = SharedControlConfig(user_cov_decay=1.0, belief_memory=0.0, goal_belief_margin=None)  # S_u fixed
    mixture = make_two_class_mixture((0.7, 0.3)).scaled(config.prior_covariance_scale)
    s_u, g_u = user_covs()
    actions = {}
    for name, obs, observed in (("far", far, [[1, 0, 0, 1, 0, 0]]), ("near", near, [[1] * 6])):
        ctrl = SharedController(HandBuiltPrior(weights=(0.7, 0.3)), config)
        ctrl.step(obs, roll)
        actions[name] = ctrl.step(obs, user)[0]
        assert ctrl.last_diagnostics.mode == "shared"
        fused = posterior.fuse_user_command(mixture, user, s_u, g_u, observed=torch.tensor(observed, dtype=torch.bool))
        expected = clamp_twist_speed(mode_search.mixture_mode(fused), config.max_linear_speed, config.max_angular_speed)
        torch.testing.assert_close(actions[name], expected[0].float(), atol=1e-5, rtol=1e-5)
    assert actions["far"][5] > 5 * actions["near"][5].abs()  # class 1 turns about z (omega_z = 2 v_x)
    assert SharedControlConfig().uncommanded_axes == "missing_unused"


def test_ood_gate_hands_control_to_user_for_three_steps_then_gives_it_back():
    prior = HandBuiltPrior()
    ctrl = SharedController(prior, SharedControlConfig.preset("paper", ood_steps=3, user_cov_decay=1.0))
    obs = make_observation()
    far = torch.tensor([[0.0, 0.0, 0.4, 0.0, 0.0, 0.0]])  # orthogonal to both classes
    near = torch.tensor([[0.27, 0.0, 0.0, 0.0, 0.0, 0.0]])
    action = ctrl.step(obs, far)
    d = ctrl.last_diagnostics
    assert d.mode == "user_only" and d.ood[0]
    torch.testing.assert_close(action, far.float())
    torch.testing.assert_close(d.class_weights, d.prior_class_weights)  # weights kept
    for _ in range(3):
        action = ctrl.step(obs, near)
        assert ctrl.last_diagnostics.mode == "user_only" and ctrl.last_diagnostics.ood[0]
        torch.testing.assert_close(action, near.float())
    action = ctrl.step(obs, near)
    assert ctrl.last_diagnostics.mode == "shared" and not ctrl.last_diagnostics.ood[0]
    assert not torch.allclose(action, near.float())
    # reset clears the window
    ctrl.step(obs, far)
    ctrl.reset()
    assert prior.resets == 1
    ctrl.step(obs, near)
    assert ctrl.last_diagnostics.mode == "shared"


def test_velocity_limits_clamp_the_norms():
    ctrl = SharedController(HandBuiltPrior(), SharedControlConfig(max_linear_speed=0.05, max_angular_speed=0.1))
    action = ctrl.step(make_observation(), None)[0]  # prior: |v| = 0.3, |w| = 0.6
    assert action[:3].norm() == pytest.approx(0.05, rel=1e-5)
    assert action[3:].norm() == pytest.approx(0.1, rel=1e-5)
    torch.testing.assert_close(action[:3] / action[:3].norm(), torch.tensor([1.0, 0.0, 0.0]))


def test_the_executed_twist_is_an_ordinary_tensor_callers_may_edit():
    # The step runs under torch.inference_mode; what it hands out must not be an inference tensor.
    ctrl = SharedController(HandBuiltPrior())
    action = ctrl.step(make_observation(), torch.tensor([[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]]))
    assert not action.is_inference()
    action.mul_(0.5)  # an in-place edit of an inference tensor outside inference mode would raise
    again = ctrl.step(make_observation(), None)  # the controller's state still works outside
    assert torch.isfinite(again).all()


def test_batched_step_mixes_modes_per_element():
    prior = HandBuiltPrior()
    ctrl = SharedController(prior)
    obs = make_observation(batch=3)
    obs[features.STATE][2, features.EE_POS] = torch.tensor([0.0, 0.0, 0.02])  # element 2 near the cloud
    user = torch.tensor([[0.0] * 6, [0.27, 0, 0, 0, 0, 0], [0.0] * 6])
    action = ctrl.step(obs, user)
    assert action.shape == (3, 6)
    assert ctrl.last_diagnostics.modes == ("autonomous", "shared", "user_only")
    assert torch.equal(action[2], torch.zeros(6))
    with pytest.raises(ValueError, match="batch size changed"):
        ctrl.step(make_observation(batch=2), None)


def test_bad_user_input_is_rejected_with_a_clear_error():
    ctrl = SharedController(HandBuiltPrior())
    with pytest.raises(ValueError, match="user_twist contains NaN"):
        ctrl.step(make_observation(), torch.tensor([[0.1, math.nan, 0, 0, 0, 0]]))
    with pytest.raises(ValueError, match=r"user_twist must have shape \(1, 6\)"):
        ctrl.step(make_observation(), torch.zeros(5))
    with pytest.raises(ValueError, match=r"user_twist must have shape \(1, 6\)"):
        ctrl.step(make_observation(), torch.zeros(6))  # unbatched
    with pytest.raises(ValueError, match="user_twist must be a floating-point array"):
        ctrl.step(make_observation(), torch.zeros(1, 6, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"must be batched \(B, 27\)"):
        ctrl.step({k: v[0] for k, v in make_observation().items()}, None)
    with pytest.raises(ValueError, match="user_twist must have shape"):
        ctrl.step(make_observation(batch=2), torch.zeros(3, 6))
    with pytest.raises(ValueError, match="observation.state"):
        ctrl.step({}, None)
    with pytest.raises(TypeError, match="predict_step0_mixture"):
        SharedController(object())
    with pytest.raises(ValueError, match="autonomy_cutoff_distance"):
        SharedControlConfig(autonomy_cutoff_distance=-1.0)


def test_empty_grasp_set_falls_back_to_user_only_without_calling_the_prior():
    prior = HandBuiltPrior()
    ctrl = SharedController(prior)
    user = torch.tensor([[0.02, 0.0, 0.0, 0.0, 0.0, 0.1]])
    action = ctrl.step(make_observation(grasps=0), user)
    d = ctrl.last_diagnostics
    assert d.mode == "user_only" and bool(d.fallback[0])
    torch.testing.assert_close(action, user)
    assert torch.equal(ctrl.step(make_observation(grasps=0), None), torch.zeros(1, 6))
    assert prior.mixture_calls == 0


def test_user_covariance_adapts_across_steps():
    ctrl = SharedController(HandBuiltPrior())
    obs = make_observation()
    rng = np.random.default_rng(6)
    for _ in range(20):
        ctrl.step(obs, (torch.from_numpy(rng.normal(0.0, 0.01, 6)) + torch.tensor([0.27, 0, 0, 0, 0, 0.54]))[None])
    s_u = ctrl.last_diagnostics.user_trans_cov[0]
    assert torch.diagonal(s_u).mean() < 0.025  # consistent user: trusted more than the initial 0.03
    assert float(torch.linalg.det(s_u)) ** (1 / 3) > 0.01


def test_fusion_presets_tuned_is_the_default_and_paper_is_the_papers_reading():
    assert SharedControlConfig() == SharedControlConfig.preset("tuned")
    paper = SharedControlConfig.preset("paper", ood_steps=2)
    assert (paper.ood_covariance, paper.ood_alpha, paper.belief_memory, paper.ood_steps) == ("class", 0.85, 0.0, 2)
    assert paper.prior_covariance_scale == 1.0 and SharedControlConfig().prior_covariance_scale == 100.0
    assert paper.goal_belief_margin is None and SharedControlConfig().goal_belief_margin == 1.0
    with pytest.raises(ValueError, match="unknown fusion preset"):
        SharedControlConfig.preset("bold")
