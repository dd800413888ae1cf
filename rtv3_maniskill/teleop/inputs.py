"""Where the user's command comes from in ``rtv3 teleop``: keyboard, gamepad (pygame) or a simulated user.

Every source has ``reset(env)`` (a new trial) and ``poll(tcp_pose, pygame_events) -> UserInput``:
the raw command of the device (``raw (6,)``, in the device's frame), the TCP body twist it means
(``body (6,)``, what the assistance method receives) and the buttons pressed this step.

A person commands in world-aligned axes at the TCP (``w`` moves the hand along world +x,
whatever its orientation); :func:`shared_control.teleop.command_frame_to_body` turns that into
the body twist. A simulated user already gives a body twist (raw = body).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from rtv3_maniskill.shared_control.simulated_users import make_user
from rtv3_maniskill.teleop.devices import (
    KEYBOARD_BUTTONS,
    XBOX_PYGAME_AXES,
    XBOX_PYGAME_BUTTONS,
    GamepadMapping,
    KeyboardMapping,
    command_frame_to_body,
    gamepad_state_from_joystick,
)


@dataclass
class UserInput:
    """One step of user input: ``raw (6,)`` device command, ``body (6,)`` TCP body twist, button events."""

    raw: torch.Tensor
    body: torch.Tensor
    buttons: list[str] = field(default_factory=list)


def _world_to_body(raw: torch.Tensor, tcp_pose: torch.Tensor) -> torch.Tensor:
    return command_frame_to_body(raw, torch.as_tensor(tcp_pose, dtype=torch.float64)[:3, :3])


class KeyboardInput:
    """Held keys of the pygame window -> twist (:class:`KeyboardMapping`); key presses -> buttons
    (:data:`KEYBOARD_BUTTONS`). Needs an open pygame window (it has the keyboard focus)."""

    name = "keyboard"

    def __init__(self, mapping: KeyboardMapping | None = None) -> None:
        import pygame  # optional extra: only the keyboard and gamepad inputs need it

        if pygame.display.get_surface() is None:
            raise RuntimeError("keyboard input needs the pygame window: run without --headless")
        self.pygame = pygame
        self.mapping = mapping or KeyboardMapping()

    def reset(self, env: Any) -> None:
        """Nothing to reset."""

    def poll(self, tcp_pose: torch.Tensor, events: list) -> UserInput:
        pg = self.pygame
        pressed = pg.key.get_pressed()
        held = {name for name in "wsadqeikjluo" if pressed[pg.key.key_code(name)]}
        buttons = [KEYBOARD_BUTTONS[e.unicode.lower()] for e in events
                   if e.type == pg.KEYDOWN and e.unicode and e.unicode.lower() in KEYBOARD_BUTTONS]
        raw = self.mapping.twist(held)
        return UserInput(raw, _world_to_body(raw, tcp_pose), buttons)


class GamepadInput:
    """The first pygame joystick (Xbox layout, :class:`GamepadMapping`); A/B/Y/X presses -> buttons."""

    name = "gamepad"

    def __init__(self, mapping: GamepadMapping | None = None, index: int = 0) -> None:
        import pygame  # optional extra: only the keyboard and gamepad inputs need it

        pygame.joystick.init()
        if pygame.joystick.get_count() <= index:
            count = pygame.joystick.get_count()
            raise RuntimeError(f"no gamepad {index}: pygame sees {count} joystick(s); plug one in")
        self.pygame = pygame
        self.joystick = pygame.joystick.Joystick(index)
        self.joystick.init()
        self.mapping = mapping or GamepadMapping()
        self._before: dict[str, bool] = {}

    def reset(self, env: Any) -> None:
        self._before = {}

    def poll(self, tcp_pose: torch.Tensor, events: list) -> UserInput:
        axes, buttons = gamepad_state_from_joystick(self.joystick, XBOX_PYGAME_AXES, XBOX_PYGAME_BUTTONS)
        now = self.mapping.events(buttons)
        pressed = [name for name, down in now.items() if down and not self._before.get(name, False)]
        self._before = now
        raw = self.mapping.twist(axes, buttons)
        return UserInput(raw, _world_to_body(raw, tcp_pose), pressed)


class SimulatedOperator:
    """A simulated user (``simulated_users.make_user``) drives to the target pre-grasp and presses the
    buttons as a person would: Y when within ``position_tolerance`` (m) and ``rotation_tolerance``
    (rad) of the pre-grasp, A when the approach has ended, X when the gripper has closed."""

    def __init__(self, user_name: str, seed: int = 0, position_tolerance: float = 0.012,
                 rotation_tolerance: float = 0.12) -> None:
        self.name = f"simulated:{user_name}"
        self.user = make_user(user_name, seed)
        self.position_tolerance = position_tolerance
        self.rotation_tolerance = rotation_tolerance
        self.env: Any = None
        self.actions: Any = None
        self._stage = 0

    def reset(self, env: Any, actions: Any = None) -> None:
        """New trial in ``env`` (a ``SharedControlEnv``); ``actions``: the session's ``GraspActions``."""
        self.env, self.actions, self._stage = env, actions, 0
        self.goal = env.user_goal()
        self.user.reset(self.goal)

    def _at_pregrasp(self, tcp_pose: torch.Tensor) -> bool:
        delta = torch.linalg.solve(self.goal, torch.as_tensor(tcp_pose, dtype=torch.float64))
        angle = float(np.arccos(np.clip((float(torch.trace(delta[:3, :3])) - 1.0) / 2.0, -1.0, 1.0)))
        return float(delta[:3, 3].norm()) < self.position_tolerance and angle < self.rotation_tolerance

    def poll(self, tcp_pose: torch.Tensor, events: list) -> UserInput:
        pose = torch.as_tensor(tcp_pose, dtype=torch.float64)
        buttons: list[str] = []
        busy = self.actions is not None and self.actions.scripted
        if not busy:
            if self._stage == 0 and self._at_pregrasp(pose):
                buttons, self._stage = ["approach"], 1
            elif self._stage in (1, 2):
                buttons = [("grasp", "lift")[self._stage - 1]]
                self._stage += 1
        twist = torch.zeros(6, dtype=torch.float64) if self._stage else self.user(pose).double()
        return UserInput(twist, twist.clone(), buttons)


def make_input(spec: str, seed: int = 0) -> Any:
    """``keyboard``, ``gamepad`` or ``simulated:NAME`` (NAME: ideal, noisy, laggy, ...) -> an input source."""
    key = str(spec).strip().lower()
    if key == "keyboard":
        return KeyboardInput()
    if key == "gamepad":
        return GamepadInput()
    if key.startswith("simulated:") and key.split(":", 1)[1]:
        return SimulatedOperator(key.split(":", 1)[1], seed)
    raise ValueError(f"unknown input {spec!r}; expected keyboard, gamepad or simulated:NAME (e.g. simulated:noisy)")


__all__ = ["GamepadInput", "KeyboardInput", "SimulatedOperator", "UserInput", "make_input"]
