"""Human input devices -> user twist ``(6,)`` ``[v (m/s), w (rad/s)]``.

Pure mapping classes (testable without a display or device) plus thin adapters around
LeRobot 0.4.4's teleoperators (imported lazily; they need a display / a gamepad at run time).

Gamepad layout, after the paper's real-world experiment ("the left joystick, left trigger
and bumper control the translation; the right joystick, trigger and bumper control the
rotation; A/B grasp/release, Y approach grasp, X lift and drop"):

=================  ==========================  ==================
input              twist component             sign
=================  ==========================  ==================
left stick x       v_x                         right = +
left stick y       v_y                         up = + (raw y is inverted)
left bumper        v_z                         +
left trigger       v_z                         -
right stick y      w_x                         up = +
right stick x      w_y                         right = +
right bumper       w_z                         +
right trigger      w_z                         -
A / B / Y / X      events grasp / release / approach / lift
=================  ==========================  ==================

Keyboard layout: ``w/s`` +-v_x, ``a/d`` +-v_y, ``q/e`` +-v_z, ``i/k`` +-w_x, ``j/l`` +-w_y,
``u/o`` +-w_z (opposite keys cancel); the buttons (:data:`KEYBOARD_BUTTONS`): ``g`` grasp (A),
``r`` release (B), ``f`` approach (Y), ``t`` lift (X).

The twist axes are those of the frame the operator commands in. The controllers take an
EE body twist; for commands meant in world-aligned axes use :func:`command_frame_to_body`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch

AXIS_NAMES = ("left_x", "left_y", "right_x", "right_y", "left_trigger", "right_trigger")
"""Gamepad axes read by :class:`GamepadMapping`: sticks in [-1, 1], triggers in [0, 1]."""
BUTTON_NAMES = ("left_bumper", "right_bumper", "a", "b", "x", "y")
"""Gamepad buttons read by :class:`GamepadMapping`."""

XBOX_PYGAME_AXES = {"left_x": 0, "left_y": 1, "left_trigger": 2, "right_x": 3, "right_y": 4, "right_trigger": 5}
"""Axis indices of an Xbox pad under pygame/SDL2 on Linux (triggers rest at -1)."""
XBOX_PYGAME_BUTTONS = {"a": 0, "b": 1, "x": 2, "y": 3, "left_bumper": 4, "right_bumper": 5}
"""Button indices of an Xbox pad under pygame/SDL2 on Linux."""


def _finite(name: str, value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"gamepad input {name!r} must be a number, got {value!r}") from err
    if not math.isfinite(x):
        raise ValueError(f"gamepad input {name!r} is NaN or inf")
    return x


def _deadzone(value: float, deadzone: float) -> float:
    """Zero inside ``deadzone``, rescaled so the output is continuous and reaches 1 at full range."""
    mag = abs(value)
    if mag <= deadzone:
        return 0.0
    return math.copysign((min(mag, 1.0) - deadzone) / (1.0 - deadzone), value)


def _radial_deadzone(x: float, y: float, deadzone: float) -> tuple[float, float]:
    """Radial deadzone on a stick ``(x, y)``, magnitude rescaled to [0, 1]."""
    mag = math.hypot(x, y)
    if mag <= deadzone:
        return 0.0, 0.0
    scale = (min(mag, 1.0) - deadzone) / ((1.0 - deadzone) * mag)
    return x * scale, y * scale


@dataclass
class GamepadMapping:
    """Xbox-style gamepad state -> twist (layout in the module docstring).

    Attributes:
        linear_speed: m/s at full deflection.
        angular_speed: rad/s at full deflection.
        deadzone: stick (radial) and trigger deadzone, in [0, 1).
        invert_y: raw stick y is negative when pushed up (pygame, SDL); flip it.
    """

    linear_speed: float = 0.15
    angular_speed: float = 0.6
    deadzone: float = 0.1
    invert_y: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.deadzone < 1.0:
            raise ValueError(f"deadzone must be in [0, 1), got {self.deadzone}")
        if not (self.linear_speed > 0 and self.angular_speed > 0):
            raise ValueError("linear_speed and angular_speed must be positive")

    def twist(self, axes: Mapping[str, float], buttons: Mapping[str, bool]) -> torch.Tensor:
        """``axes`` (names in :data:`AXIS_NAMES`; missing = 0) and ``buttons`` -> ``(6,)`` float64 twist."""
        unknown = set(axes) - set(AXIS_NAMES)
        if unknown:
            raise ValueError(f"unknown gamepad axes {sorted(unknown)}; known: {AXIS_NAMES}")
        a = {name: max(-1.0, min(1.0, _finite(name, axes.get(name, 0.0)))) for name in AXIS_NAMES}
        b = {name: bool(buttons.get(name, False)) for name in ("left_bumper", "right_bumper")}
        sign_y = -1.0 if self.invert_y else 1.0
        lx, ly = _radial_deadzone(a["left_x"], sign_y * a["left_y"], self.deadzone)
        rx, ry = _radial_deadzone(a["right_x"], sign_y * a["right_y"], self.deadzone)
        lt = _deadzone(max(0.0, a["left_trigger"]), self.deadzone)
        rt = _deadzone(max(0.0, a["right_trigger"]), self.deadzone)
        v = [lx, ly, float(b["left_bumper"]) - lt]
        w = [ry, rx, float(b["right_bumper"]) - rt]
        return torch.tensor([self.linear_speed * x for x in v] + [self.angular_speed * x for x in w],
                            dtype=torch.float64)

    @staticmethod
    def events(buttons: Mapping[str, bool]) -> dict[str, bool]:
        """Discrete commands of the paper's layout: grasp (A), release (B), approach (Y), lift (X)."""
        return {
            "grasp": bool(buttons.get("a", False)),
            "release": bool(buttons.get("b", False)),
            "approach": bool(buttons.get("y", False)),
            "lift": bool(buttons.get("x", False)),
        }


KEYBOARD_LAYOUT: dict[str, tuple[int, float]] = {
    "w": (0, 1.0), "s": (0, -1.0), "a": (1, 1.0), "d": (1, -1.0), "q": (2, 1.0), "e": (2, -1.0),
    "i": (3, 1.0), "k": (3, -1.0), "j": (4, 1.0), "l": (4, -1.0), "u": (5, 1.0), "o": (5, -1.0),
}  # fmt: skip
"""Key -> (twist index, sign)."""
KEYBOARD_BUTTONS: dict[str, str] = {"g": "grasp", "r": "release", "f": "approach", "t": "lift"}
"""Key -> button event (the gamepad's A, B, Y, X; see :meth:`GamepadMapping.events`)."""


@dataclass
class KeyboardMapping:
    """Set of held keys -> twist (layout in the module docstring); other keys are ignored."""

    linear_speed: float = 0.15
    angular_speed: float = 0.6

    def __post_init__(self) -> None:
        if not (self.linear_speed > 0 and self.angular_speed > 0):
            raise ValueError("linear_speed and angular_speed must be positive")

    def twist(self, pressed_keys: set[str] | frozenset[str]) -> torch.Tensor:
        """``pressed_keys`` (single characters, any case) -> ``(6,)`` float64 twist."""
        out = torch.zeros(6, dtype=torch.float64)
        for key in {str(k).lower() for k in pressed_keys if isinstance(k, str)}:
            if key in KEYBOARD_LAYOUT:
                idx, sign = KEYBOARD_LAYOUT[key]
                out[idx] += sign * (self.linear_speed if idx < 3 else self.angular_speed)
        return out


def command_frame_to_body(twist: torch.Tensor, ee_rotation: torch.Tensor) -> torch.Tensor:
    """A twist ``(6,)`` with world-aligned axes at the EE point -> EE body twist ``[R^T v, R^T w]``.

    ``ee_rotation``: ``(3, 3)`` EE orientation in the world.
    """
    rot_t = ee_rotation.to(twist.dtype).transpose(-1, -2)
    return torch.cat([rot_t @ twist[:3], rot_t @ twist[3:]])


# --------------------------------------------------------------------------- LeRobot adapters


def pressed_keys_from_keyboard_action(action: Mapping[Any, Any]) -> set[str]:
    """``lerobot.teleoperators.keyboard.KeyboardTeleop.get_action()`` returns ``{key_char: None}``
    for every held key; this returns the set of held character keys."""
    return {k for k in action if isinstance(k, str)}


def gamepad_state_from_joystick(
    joystick: Any,
    axis_indices: Mapping[str, int] = XBOX_PYGAME_AXES,
    button_indices: Mapping[str, int] = XBOX_PYGAME_BUTTONS,
    trigger_rest: float = -1.0,
) -> tuple[dict[str, float], dict[str, bool]]:
    """Read a pygame-style joystick (``get_axis(i)``, ``get_button(i)``) into the named axes and
    buttons :class:`GamepadMapping` takes. Trigger axes resting at ``trigger_rest`` are mapped to [0, 1]."""
    axes = {}
    for name, idx in axis_indices.items():
        raw = float(joystick.get_axis(idx))
        if name.endswith("_trigger"):
            raw = (raw - trigger_rest) / (1.0 - trigger_rest)
        axes[name] = raw
    buttons = {name: bool(joystick.get_button(idx)) for name, idx in button_indices.items()}
    return axes, buttons


class LeRobotKeyboardTwist:
    """User twist from LeRobot's ``KeyboardTeleop`` (pynput; needs a display)."""

    def __init__(self, mapping: KeyboardMapping | None = None, teleop: Any = None) -> None:
        self.mapping = mapping or KeyboardMapping()
        self.teleop = teleop

    def connect(self) -> None:
        """Create (if needed) and connect the LeRobot keyboard teleoperator."""
        if self.teleop is None:
            from lerobot.teleoperators.keyboard import KeyboardTeleop, KeyboardTeleopConfig

            self.teleop = KeyboardTeleop(KeyboardTeleopConfig())
        self.teleop.connect()

    def twist(self) -> torch.Tensor:
        """Current ``(6,)`` twist from the held keys."""
        if self.teleop is None:
            raise RuntimeError("call connect() first")
        if not self.teleop.is_connected:
            raise RuntimeError(
                "LeRobot keyboard teleoperator is not connected: pynput needs a display (DISPLAY unset?)"
            )
        return self.mapping.twist(pressed_keys_from_keyboard_action(self.teleop.get_action()))

    def disconnect(self) -> None:
        if self.teleop is not None:
            self.teleop.disconnect()


class LeRobotGamepadTwist:
    """User twist from LeRobot's ``GamepadTeleop`` (pygame; needs a gamepad).

    LeRobot's ``get_action()`` gives only three translation deltas, so this adapter lets
    LeRobot open the device and then reads all axes/buttons of its pygame joystick
    (``teleop.gamepad.joystick``) with the Xbox/SDL2 indices (configurable).
    """

    def __init__(
        self,
        mapping: GamepadMapping | None = None,
        teleop: Any = None,
        axis_indices: Mapping[str, int] = XBOX_PYGAME_AXES,
        button_indices: Mapping[str, int] = XBOX_PYGAME_BUTTONS,
        trigger_rest: float = -1.0,
    ) -> None:
        self.mapping = mapping or GamepadMapping()
        self.teleop = teleop
        self.axis_indices = dict(axis_indices)
        self.button_indices = dict(button_indices)
        self.trigger_rest = trigger_rest
        self.last_events: dict[str, bool] = {}

    def connect(self) -> None:
        """Create (if needed) and connect the LeRobot gamepad teleoperator."""
        if self.teleop is None:
            from lerobot.teleoperators.gamepad import GamepadTeleop, GamepadTeleopConfig

            self.teleop = GamepadTeleop(GamepadTeleopConfig(use_gripper=False))
        self.teleop.connect()

    def twist(self) -> torch.Tensor:
        """Current ``(6,)`` twist; the A/B/X/Y events land in ``last_events``."""
        controller = getattr(self.teleop, "gamepad", None)
        joystick = getattr(controller, "joystick", None)
        if joystick is None:
            raise RuntimeError(
                "no pygame joystick: call connect() with a gamepad attached (Linux/Windows pygame backend)")
        controller.update()
        axes, buttons = gamepad_state_from_joystick(joystick, self.axis_indices, self.button_indices, self.trigger_rest)
        self.last_events = self.mapping.events(buttons)
        return self.mapping.twist(axes, buttons)

    def disconnect(self) -> None:
        if self.teleop is not None:
            self.teleop.disconnect()
