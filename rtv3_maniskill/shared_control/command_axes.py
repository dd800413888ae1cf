"""Which axes of a user command the posterior fuses (paper, Sec. V, user twist likelihood).

A command ``u (B, 6)`` ``[v, w]`` with some axes at zero (``|u_i| <= input_threshold``) may come
from a device that does not give those axes (a mode-switching or single-axis user) or from a user
who wants the robot to hold still along them. An axis the posterior does not observe is a missing
measurement (:func:`~rtv3_maniskill.shared_control.posterior.fuse_user_command`, ``observed``): the
prior fills it in. :func:`observed_axes` decides, per element and axis, under one of
:data:`UNCOMMANDED_AXES`.
"""

from __future__ import annotations

import torch

UNCOMMANDED_AXES = ("missing", "zero", "missing_far", "missing_far_group", "missing_unused",
                    "missing_unused_group")
"""How a zero axis of a command that is not zero altogether is read (``SharedControlConfig.uncommanded_axes``)."""


def observed_axes(rule: str, commanded: torch.Tensor, used: torch.Tensor, near: torch.Tensor) -> torch.Tensor:
    """``(B, 6)`` bool: the axes of this step's command that carry an observation.

    Args:
        rule: one of :data:`UNCOMMANDED_AXES`.
        commanded: ``(B, 6)`` bool, the axes this command gives.
        used: ``(B, 6)`` bool, the axes the user has commanded since the episode started.
        near: ``(B,)`` bool, the EE is within the autonomy cutoff of the scene.
    """
    if rule not in UNCOMMANDED_AXES:
        raise ValueError(f"uncommanded_axes must be one of {UNCOMMANDED_AXES}, got {rule!r}")
    if rule == "missing":
        return commanded
    if rule == "zero":
        return torch.ones_like(commanded)
    b = commanded.shape[0]
    used_kind = used.view(b, 2, 3).any(-1, keepdim=True).expand(b, 2, 3).reshape(b, 6)
    near = near[:, None]
    if rule == "missing_far":
        return commanded | (used & near)
    if rule == "missing_far_group":
        return commanded | (used_kind & near)
    if rule == "missing_unused":
        return commanded | used | (used_kind & near)
    return commanded | used_kind  # missing_unused_group
