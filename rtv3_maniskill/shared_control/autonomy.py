"""Asynchronous mode (paper, Sec. V): what the controller does when the user gives no command.

Far from the scene the controller executes the prior's most likely step-0 twist
(:func:`most_likely_twist`); within a cutoff of the scene (:func:`surface_distance` to the point
cloud and the table top) the user keeps control. Positions are world frame (m); twists EE body
frame ``[v (m/s), w (rad/s)]``.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from rtv3_maniskill import features
from rtv3_maniskill.shared_control.posterior import FactorizedTwistMixture


def surface_distance(observation: dict[str, Any], table_height: float | None = None) -> torch.Tensor:
    """``(B,)`` distance (m) from the EE position (``observation.state[..., EE_POS]``, world) to the
    nearest valid point of ``observation.point_cloud`` (world xyz), or to the table top (the plane
    z = ``table_height``) where that is nearer; inf without either."""
    state = torch.as_tensor(observation[features.STATE])
    ee = (state[None] if state.ndim == 1 else state)[:, features.EE_POS].double()
    dist = _cloud_distance(observation, ee)
    return dist if table_height is None else torch.minimum(dist, ee[:, 2] - table_height)


def _cloud_distance(observation: dict[str, Any], ee: torch.Tensor) -> torch.Tensor:
    """``(B,)`` distance from ``ee (B, 3)`` to the nearest valid cloud point; inf without one."""
    b = ee.shape[0]
    if features.POINT_CLOUD not in observation:
        return torch.full((b,), math.inf, dtype=torch.float64)
    cloud = features.unflatten(features.POINT_CLOUD, torch.as_tensor(observation[features.POINT_CLOUD]))
    cloud = (cloud[None] if cloud.ndim == 2 else cloud)[..., :3].double()
    if cloud.shape[0] != b:
        raise ValueError(f"{features.POINT_CLOUD} has batch {cloud.shape[0]}, state has {b}")
    if features.POINT_CLOUD_MASK in observation:
        mask = torch.as_tensor(observation[features.POINT_CLOUD_MASK])
        mask = (mask[None] if mask.ndim == 1 else mask) > 0.5
    else:
        mask = torch.ones(cloud.shape[:2], dtype=torch.bool)
    mask = mask & torch.isfinite(cloud).all(-1)
    dist = (cloud - ee[:, None]).norm(dim=-1)
    dist = torch.where(mask, dist, torch.full_like(dist, math.inf))
    return dist.min(-1).values if dist.shape[1] > 0 else torch.full((b,), math.inf, dtype=torch.float64)


def most_likely_twist(prior: FactorizedTwistMixture) -> torch.Tensor:
    """The prior's most likely step-0 action ``(B, 6)``: the argmax class, the mean of its
    translation Gaussian, then the mean of its rotation Gaussian given that translation
    (docs/PAPER_DETAILS.md "Most-Likely"; the same as the policy's ``select_action``). ``prior`` is
    :func:`posterior.prior_twist_mixture`, whose rotation Gaussians already sit at the
    translation means, so no second pass through the network is needed."""
    best = prior.log_weights.argmax(-1)
    return prior.means[torch.arange(best.shape[0], device=best.device), best]
