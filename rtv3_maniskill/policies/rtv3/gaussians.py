"""Gaussian action distributions of the RT-V3 decoder (Eq. velocitygmm, rotgmm).

Log-densities use ``log det Sigma`` (the authors' code used ``det``, a known bug; docs/PAPER_DETAILS.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import torch

from rtv3_maniskill import se3

_LOG_2PI = math.log(2 * math.pi)


@dataclass
class AxisGaussian:
    """3-D Gaussian with full covariance ``Sigma = R diag(sigma^2) R^T``.

    Attributes:
        mean: ``(..., 3)``.
        log_sigma: ``(..., 3)`` log standard deviations along the principal axes.
        axes_rotvec: ``(..., 3)`` rotation vector of ``R``, whose columns are the principal axes
            (``axes``, built on first use: the most-likely rollout needs only the means).
    """

    mean: torch.Tensor
    log_sigma: torch.Tensor
    axes_rotvec: torch.Tensor

    @cached_property
    def axes(self) -> torch.Tensor:
        """``(..., 3, 3)`` rotation ``R = Exp(axes_rotvec)``."""
        return se3.so3_exp(self.axes_rotvec)

    @classmethod
    def from_raw(cls, raw: torch.Tensor, log_sigma_min: float, log_sigma_max: float) -> AxisGaussian:
        """``raw (..., 9)`` = [mean (3), log sigma (3), rotation vector of the axes (3)]."""
        return cls(
            mean=raw[..., 0:3],
            log_sigma=raw[..., 3:6].clamp(log_sigma_min, log_sigma_max),
            axes_rotvec=raw[..., 6:9],
        )

    def covariance(self) -> torch.Tensor:
        """``(..., 3, 3)`` symmetric positive definite covariance."""
        scaled = self.axes * torch.exp(self.log_sigma)[..., None, :]
        return scaled @ scaled.transpose(-1, -2)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """``log N(value; mean, Sigma)`` with ``log det Sigma = 2 sum log sigma``: ``(...)``."""
        local = ((value - self.mean)[..., None, :] @ self.axes)[..., 0, :]  # R^T (y - mu)
        maha = (local * torch.exp(-self.log_sigma)).pow(2).sum(-1)
        return -0.5 * maha - self.log_sigma.sum(-1) - 1.5 * _LOG_2PI

    def sample(self) -> torch.Tensor:
        """One draw ``mu + R diag(sigma) eps``, ``eps ~ N(0, I)``: ``(..., 3)`` (reparameterised)."""
        eps = torch.randn_like(self.mean) * torch.exp(self.log_sigma)
        return self.mean + (self.axes @ eps[..., None])[..., 0]

    def scaled(self, factor: float) -> AxisGaussian:
        """The distribution of ``factor * y`` (used to undo the translation scale)."""
        return AxisGaussian(self.mean * factor, self.log_sigma + math.log(factor), self.axes_rotvec)


@dataclass
class JointGaussian:
    """6-D Gaussian over ``[v, w]`` with Cholesky factor ``L`` (``Sigma = L L^T``), the "6D pred" head.

    Attributes:
        mean: ``(..., 6)``.
        scale_tril: ``(..., 6, 6)`` lower triangular with positive diagonal.
    """

    mean: torch.Tensor
    scale_tril: torch.Tensor

    RAW_DIM = 6 + 6 + 15

    @classmethod
    def from_raw(cls, raw: torch.Tensor, log_sigma_min: float, log_sigma_max: float) -> JointGaussian:
        """``raw (..., 27)`` = [mean (6), log diag (6), strictly-lower entries (15)]."""
        lead = raw.shape[:-1]
        tril = raw.new_zeros(*lead, 6, 6)
        rows, cols = torch.tril_indices(6, 6, offset=-1, device=raw.device)
        tril[..., rows, cols] = raw[..., 12:27]
        diag = torch.exp(raw[..., 6:12].clamp(log_sigma_min, log_sigma_max))
        return cls(mean=raw[..., :6], scale_tril=tril + torch.diag_embed(diag))

    def covariance(self) -> torch.Tensor:
        return self.scale_tril @ self.scale_tril.transpose(-1, -2)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """``(...)`` log-density; ``log det Sigma = 2 sum log diag L``."""
        diff = (value - self.mean)[..., None]
        white = torch.linalg.solve_triangular(self.scale_tril, diff, upper=False)[..., 0]
        log_det_half = torch.log(torch.diagonal(self.scale_tril, dim1=-2, dim2=-1)).sum(-1)
        return -0.5 * white.pow(2).sum(-1) - log_det_half - 3.0 * _LOG_2PI

    def split(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(mu_v, mu_w, Sigma_vv, [Sigma_vw; Sigma_ww])`` blocks."""
        cov = self.covariance()
        return self.mean[..., :3], self.mean[..., 3:], cov[..., :3, :3], cov[..., 3:, :]

    def rotation_given_translation(self, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaussian conditional ``p(w | v)``: ``omega = mu_w + S_wv S_vv^-1 (v - mu_v)``, Schur complement."""
        cov = self.covariance()
        s_vv, s_wv, s_ww = cov[..., :3, :3], cov[..., 3:, :3], cov[..., 3:, 3:]
        gain = torch.linalg.solve(s_vv, s_wv.transpose(-1, -2)).transpose(-1, -2)  # S_wv S_vv^-1
        omega = self.mean[..., 3:] + (gain @ (v - self.mean[..., :3])[..., None])[..., 0]
        gamma = s_ww - gain @ s_wv.transpose(-1, -2)
        return omega, 0.5 * (gamma + gamma.transpose(-1, -2))
