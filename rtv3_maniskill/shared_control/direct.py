"""Direct teleoperation baseline ("Direct" in the paper): the user's twist is executed as is."""

from __future__ import annotations

from typing import Any

import torch

from rtv3_maniskill.shared_control.twist_utils import as_pose, as_twist, check_speed_limits, clamp_twist_speed


class DirectTeleoperation:
    """Pass the user body twist through, norm-clipped to the velocity limits.

    Same call shape as :class:`HindsightOptimization` so benchmarks can swap them.
    """

    def __init__(self, max_linear_speed: float | None = 0.5, max_angular_speed: float | None = 1.5) -> None:
        check_speed_limits(max_linear_speed, max_angular_speed)
        self.max_linear_speed = max_linear_speed
        self.max_angular_speed = max_angular_speed

    def reset(self) -> None:
        """Nothing to reset (stateless)."""

    def step(self, ee_pose: Any, user_twist: Any) -> torch.Tensor:
        """``ee_pose (4, 4)`` (checked, otherwise unused), ``user_twist (6,)`` -> ``(6,)`` float64 twist."""
        if ee_pose is not None:
            as_pose(ee_pose)
        twist = as_twist(user_twist, "user_twist")
        return clamp_twist_speed(twist, self.max_linear_speed, self.max_angular_speed)
