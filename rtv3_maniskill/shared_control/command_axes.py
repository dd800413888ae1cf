"""Which axes of a user command the posterior fuses (paper, Sec. V, user twist likelihood).

A command ``u (B, 6)`` ``[v, w]`` with some axes at zero (``|u_i| <= input_threshold``) may come
from a device that does not give those axes (a mode-switching or single-axis user) or from a user
who wants the robot to hold still along them. An axis the posterior does not observe is a missing
measurement (:func:`~rtv3_maniskill.shared_control.posterior.fuse_user_command`, ``observed``): the
prior fills it in; an observed zero axis means "hold still". :func:`observed_axes` decides per
element and axis under one of :data:`UNCOMMANDED_AXES`:

* ``"missing"``: every zero axis is missing (the paper preset);
* ``"missing_unused"``: a zero axis is missing only while the user has never commanded it since
  the episode started and the EE is farther than the autonomy cutoff from the scene. An axis the
  user has commanded and then left is held still (the prior does not continue the user's earlier
  motion along it), and near the scene every axis of a kind (translation or rotation) the user has
  commanded is held still (the prior does not turn or push the hand about axes the user has not
  reached yet, close to clutter). The tuned preset.
"""

from __future__ import annotations

import torch

UNCOMMANDED_AXES = ("missing", "missing_unused")
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
    b = commanded.shape[0]
    used_kind = used.view(b, 2, 3).any(-1, keepdim=True).expand(b, 2, 3).reshape(b, 6)
    return commanded | used | (used_kind & near[:, None])
