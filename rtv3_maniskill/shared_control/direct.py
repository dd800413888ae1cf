"""Direct teleoperation baseline ("Direct" in the paper): the user's twist is executed as is."""

from __future__ import annotations

from typing import Any

import torch

from rtv3_maniskill.shared_control.twist_utils import check_speed_limits, clamp_twist_speed, step_inputs


class DirectTeleoperation:
    """Pass the user body twist through, norm-clipped to the velocity limits.

    Args:
        max_linear_speed, max_angular_speed: norm limits (m/s, rad/s) of the output; None = none.
    """

    name = "direct"

    def __init__(self, max_linear_speed: float | None = 0.3, max_angular_speed: float | None = 1.2) -> None:
        check_speed_limits(max_linear_speed, max_angular_speed)
        self.max_linear_speed = max_linear_speed
        self.max_angular_speed = max_angular_speed

    def reset(self) -> None:
        """Nothing to forget (stateless)."""

    def step(self, observation: dict[str, Any], user_twist: Any) -> torch.Tensor:
        """``observation`` (``observation.state (B, 27)``), ``user_twist (B, 6)`` or None -> ``(B, 6)`` float32."""
        _, user = step_inputs(observation, user_twist)
        return clamp_twist_speed(user, self.max_linear_speed, self.max_angular_speed)

    def describe(self, index: int = 0) -> dict[str, Any]:
        """The last step of batch element ``index``: the user alone drives."""
        return {"mode": "user_only"}
