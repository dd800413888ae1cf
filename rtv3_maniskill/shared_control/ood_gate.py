"""The out-of-distribution gate on the user command (paper, Sec. V; docs/PAPER_DETAILS.md).

A command farther than ``chi2.ppf(alpha, d)`` (squared Mahalanobis distance over its ``d``
observed axes) from every maneuver class is out of the prior's distribution: the controller
then executes the user's own command for a few steps instead of fusing it.
"""

from __future__ import annotations

import functools
import math

import torch

from rtv3_maniskill.shared_control.posterior import FactorizedTwistMixture


@functools.lru_cache(maxsize=64)
def ood_threshold(alpha: float = 0.85, dof: int = 3) -> float:
    """``chi2.ppf(alpha, dof)``: the gate on the squared Mahalanobis distance (docs/PAPER_DETAILS.md)."""
    from scipy.stats import chi2

    if not 0.0 < alpha < 1.0:
        raise ValueError(f"OOD alpha must be in (0, 1), got {alpha}")
    return float(chi2.ppf(alpha, dof))


OOD_COVARIANCES = ("class", "predictive")
"""Covariances of the OOD test's Mahalanobis distance (see :func:`is_out_of_distribution`)."""


def is_out_of_distribution(fused: FactorizedTwistMixture, alpha: float, covariance: str = "class") -> torch.Tensor:
    """``(B,)`` bool: the user command is farther than ``chi2.ppf(alpha, d)`` (squared Mahalanobis,
    ``d`` the number of observed axes) from *every* class, i.e. from the nearest one.

    The distance to a class is the sum of the translation and rotation distances (``v_u`` and
    ``w_u`` are independent given the class), over the observed axes of the command only
    (``fused.observed``; the marginal distance, ``d`` = their number); with none observed the
    command is never OOD.

    ``covariance``: ``"class"`` measures the distance under each class's own covariance
    (docs/PAPER_DETAILS.md: "the Mahalanobis distance of the user translation to the nearest
    class": is the command a plausible draw of one of the prior's maneuvers?); ``"predictive"``
    adds the user covariance (``Sigma_k + S_u``: the density of a noisy command).
    """
    if covariance not in OOD_COVARIANCES:
        raise ValueError(f"covariance must be one of {OOD_COVARIANCES}, got {covariance!r}")
    if covariance == "class":
        trans, rot = fused.trans_class_mahalanobis_sq, fused.rot_class_mahalanobis_sq
    else:
        trans, rot = fused.trans_mahalanobis_sq, fused.rot_mahalanobis_sq
    if trans is None or rot is None or fused.observed is None:
        raise ValueError("this mixture carries no user command (use fuse_user_command)")
    tested = fused.observed.sum(-1)
    maha = trans + rot
    thresholds = torch.tensor([math.inf] + [ood_threshold(alpha, d) for d in range(1, 7)], dtype=maha.dtype)
    return maha.min(-1).values > thresholds[tested]
