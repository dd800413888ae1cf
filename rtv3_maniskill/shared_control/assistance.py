"""The interface every assistance method shares (Direct, HO, RT-V3); :mod:`~rtv3_maniskill.shared_control.methods`
lists them by name."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch


@runtime_checkable
class AssistanceMethod(Protocol):
    """Turns the user's twist into the robot's twist, one control step at a time.

    ``step(observation, user_twist)``: ``observation`` is a batched feature dict
    (``rtv3_maniskill.features``: at least ``observation.state (B, 27)``), ``user_twist`` a
    ``(B, 6)`` body twist ``[v (m/s), w (rad/s)]`` in the TCP frame or None (no input); returns the
    robot's ``(B, 6)`` float32 body twist. Inputs are checked once, on entry
    (:func:`~rtv3_maniskill.shared_control.twist_utils.step_inputs`). ``reset()`` starts an
    episode; ``describe(index)`` tells what the last step did for batch element ``index``
    (``"mode"``: ``"shared"``, ``"autonomous"`` or ``"user_only"``, plus the method's own state).
    """

    name: str

    def reset(self) -> None: ...

    def step(self, observation: dict[str, Any], user_twist: Any) -> torch.Tensor: ...

    def describe(self, index: int = 0) -> dict[str, Any]: ...
