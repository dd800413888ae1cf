"""The step-0 action distribution the prior hands to the posterior (paper, Sec. V).

Per maneuver class ``z`` (K classes) the prior gives a translation Gaussian
``N(v; mu_z, Sigma_z)`` (Eq. velocitygmm) and, *conditioned on a translation* ``v``, a
rotation Gaussian ``N(w; omega_z(v), Gamma_z(v))`` (Eq. rotgmm). Because of that
conditioning the rotation part is a function, not a tensor.

Units: m/s and rad/s, body frame of the current end-effector pose (any training-time
scaling already undone).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import torch

RotationGivenTranslation = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""``v (..., B, K, 3) -> (omega (..., B, K, 3), Gamma (..., B, K, 3, 3))``: leading dimensions
hold several translations per class, evaluated in one call (the posterior needs two)."""


@dataclass
class TwistMixture:
    """Gaussian mixture over the step-0 body twist ``a_0 = [v_0, w_0]``.

    Attributes:
        log_weights: ``(B, K)`` log p(z | h_0), normalised (logsumexp = 0).
        trans_mean: ``(B, K, 3)`` mu_z.
        trans_cov: ``(B, K, 3, 3)`` Sigma_z, symmetric positive definite.
        rotation_given_translation: callable giving (omega_z, Gamma_z) for a translation per class.
    """

    log_weights: torch.Tensor
    trans_mean: torch.Tensor
    trans_cov: torch.Tensor
    rotation_given_translation: RotationGivenTranslation

    @property
    def weights(self) -> torch.Tensor:
        """``(B, K)`` class probabilities."""
        return self.log_weights.exp()

    @property
    def num_classes(self) -> int:
        return self.log_weights.shape[-1]

    def scaled(self, scale: float) -> TwistMixture:
        """This mixture with every class covariance (translation ``Sigma_z``, rotation ``Gamma_z``)
        times ``scale``; the means and weights are kept (``self`` when ``scale`` is 1)."""
        if scale == 1.0:
            return self
        rotation = self.rotation_given_translation

        def scaled_rotation(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            omega, gamma = rotation(v)
            return omega, gamma * scale

        return dataclasses.replace(self, trans_cov=self.trans_cov * scale, rotation_given_translation=scaled_rotation)
