"""The paper's grasp buttons as a state machine: A grasps, B releases, Y approaches, X lifts.

Between button presses the user (through the assistance method) drives the TCP; a button starts
a scripted motion that runs to its end on its own (the person only watches):

* ``approach`` (Y): straight along the tool z axis (the approach axis) by ``approach_distance``
  (5 cm: from the pre-grasp to the grasp);
* ``grasp`` (A): hold still and close the gripper for ``close_steps``; it then stays closed;
* ``lift`` (X): straight up (world +z) by ``lift_height``, gripper as it is;
* ``release`` (B): hold still and open the gripper for ``open_steps`` (also aborts a motion).

Other buttons pressed during a scripted motion are ignored. Gripper commands are ManiSkill's
normalised Panda gripper action (``features.GRIPPER_OPEN`` = 1, ``features.GRIPPER_CLOSED`` = -1).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from rtv3_maniskill.features import DT, GRIPPER_CLOSED, GRIPPER_OPEN, PREGRASP_DISTANCE
from rtv3_maniskill.teleop.recorder import BUTTON_EVENTS

EVENTS = BUTTON_EVENTS
"""Button events in the order they are recorded (``button_events (4,)``): A, B, Y, X."""
PHASES = ("free", "approach", "closing", "lifting", "opening")
"""``free``: the user drives; the others are scripted motions."""


@dataclass
class GraspActionConfig:
    """Scripted motion settings (m, m/s, control steps at 20 Hz)."""

    approach_distance: float = PREGRASP_DISTANCE
    approach_speed: float = 0.05
    close_steps: int = 15
    lift_height: float = 0.10
    lift_speed: float = 0.05
    open_steps: int = 10

    def __post_init__(self) -> None:
        for name in ("approach_distance", "approach_speed", "lift_height", "lift_speed"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.close_steps < 1 or self.open_steps < 1:
            raise ValueError("close_steps and open_steps must be >= 1")


class GraspActions:
    """Button events -> scripted TCP motion and gripper command, one control step at a time."""

    def __init__(self, config: GraspActionConfig | None = None) -> None:
        self.config = config or GraspActionConfig()
        self.reset()

    def reset(self) -> None:
        """Gripper open, user in control."""
        self.phase = "free"
        self.gripper = GRIPPER_OPEN
        self._start: torch.Tensor | None = None
        self._count = 0

    @property
    def scripted(self) -> bool:
        """True while a scripted motion runs (the user's command is ignored)."""
        return self.phase != "free"

    def press(self, event: str) -> bool:
        """Register a button ``event`` (one of :data:`EVENTS`); returns whether it started something."""
        if event not in EVENTS:
            raise ValueError(f"unknown button event {event!r}; known: {EVENTS}")
        if event == "release":
            self.phase, self._count, self.gripper = "opening", 0, GRIPPER_OPEN
            return True
        if self.scripted:
            return False
        self._start, self._count = None, 0
        if event == "approach":
            self.phase = "approach"
        elif event == "grasp":
            self.phase, self.gripper = "closing", GRIPPER_CLOSED
        else:
            self.phase = "lifting"
        return True

    def step(self, tcp_pose: torch.Tensor) -> torch.Tensor | None:
        """The scripted body twist ``(6,)`` float64 (TCP frame) for this step, or None when the user drives.

        ``tcp_pose``: ``(4, 4)`` current TCP pose (world). The gripper command is :attr:`gripper`.
        """
        pose = torch.as_tensor(tcp_pose, dtype=torch.float64)
        if pose.shape != (4, 4):
            raise ValueError(f"tcp_pose must be (4, 4), got {tuple(pose.shape)}")
        cfg = self.config
        if self.phase == "free":
            return None
        if self._start is None:
            self._start = pose.clone()
        twist = torch.zeros(6, dtype=torch.float64)
        if self.phase in ("closing", "opening"):
            self._count += 1
            if self._count >= (cfg.close_steps if self.phase == "closing" else cfg.open_steps):
                self.phase = "free"
            return twist
        if self.phase == "approach":
            axis, distance, speed = self._start[:3, 2], cfg.approach_distance, cfg.approach_speed
        else:
            axis, distance, speed = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), cfg.lift_height, cfg.lift_speed
        remaining = distance - float((pose[:3, 3] - self._start[:3, 3]) @ axis)
        self._count += 1
        if remaining <= 1e-3 or self._count > 3 * distance / (speed * DT):  # done (or stuck against something)
            self.phase = "free"
            return twist
        world_v = axis * min(speed, remaining / DT)
        twist[:3] = pose[:3, :3].T @ world_v  # world velocity -> TCP body frame
        return twist


__all__ = ["EVENTS", "PHASES", "GraspActionConfig", "GraspActions"]
