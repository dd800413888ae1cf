"""Keyboard / gamepad -> user twist mappings and the LeRobot teleoperator adapters."""

from __future__ import annotations

import math

import pytest
import torch

from rtv3_maniskill.se3 import so3_exp
from rtv3_maniskill.teleop.devices import (
    GamepadMapping,
    KeyboardMapping,
    LeRobotKeyboardTwist,
    command_frame_to_body,
    gamepad_state_from_joystick,
    pressed_keys_from_keyboard_action,
)

F64 = torch.float64


def basis(i: int, scale: float) -> torch.Tensor:
    out = torch.zeros(6, dtype=F64)
    out[i] = scale
    return out


@pytest.mark.parametrize(
    "key, index, sign",
    [("w", 0, 1), ("s", 0, -1), ("a", 1, 1), ("d", 1, -1), ("q", 2, 1), ("e", 2, -1),
     ("i", 3, 1), ("k", 3, -1), ("j", 4, 1), ("l", 4, -1), ("u", 5, 1), ("o", 5, -1)],
)  # fmt: skip
def test_keyboard_layout(key, index, sign):
    mapping = KeyboardMapping(linear_speed=0.2, angular_speed=0.7)
    torch.testing.assert_close(mapping.twist({key}), basis(index, sign * (0.2 if index < 3 else 0.7)))


def test_keyboard_combines_cancels_and_ignores_other_keys():
    mapping = KeyboardMapping(linear_speed=0.1, angular_speed=0.5)
    torch.testing.assert_close(mapping.twist({"W", "u", "x", "space"}), basis(0, 0.1) + basis(5, 0.5))
    assert torch.equal(mapping.twist({"w", "s"}), torch.zeros(6, dtype=F64))
    assert torch.equal(mapping.twist(set()), torch.zeros(6, dtype=F64))


def test_gamepad_paper_layout_left_translation_right_rotation():
    pad = GamepadMapping(linear_speed=0.2, angular_speed=0.8, deadzone=0.1)
    torch.testing.assert_close(pad.twist({"left_x": 1.0}, {}), basis(0, 0.2))
    torch.testing.assert_close(pad.twist({"left_y": -1.0}, {}), basis(1, 0.2))  # stick pushed up
    torch.testing.assert_close(pad.twist({}, {"left_bumper": True}), basis(2, 0.2))
    torch.testing.assert_close(pad.twist({"left_trigger": 1.0}, {}), basis(2, -0.2))
    torch.testing.assert_close(pad.twist({"right_y": -1.0}, {}), basis(3, 0.8))
    torch.testing.assert_close(pad.twist({"right_x": 1.0}, {}), basis(4, 0.8))
    torch.testing.assert_close(pad.twist({}, {"right_bumper": True}), basis(5, 0.8))
    torch.testing.assert_close(pad.twist({"right_trigger": 1.0}, {}), basis(5, -0.8))
    events = pad.events({"a": True, "y": True})
    assert events == {"grasp": True, "release": False, "approach": True, "lift": False}


def test_gamepad_deadzone_is_continuous_and_scaled():
    pad = GamepadMapping(linear_speed=1.0, angular_speed=1.0, deadzone=0.2)
    assert torch.equal(pad.twist({"left_x": 0.15, "left_y": 0.1, "right_trigger": 0.19}, {}), torch.zeros(6, dtype=F64))
    just_out = pad.twist({"left_x": 0.2001}, {})
    assert 0 < just_out[0] < 1e-3
    torch.testing.assert_close(pad.twist({"left_x": 0.6}, {}), basis(0, 0.5))  # (0.6 - 0.2) / 0.8
    diag = pad.twist({"left_x": 1.0, "left_y": -1.0}, {})
    assert float(diag[:2].norm()) == pytest.approx(1.0)  # radial: full deflection caps at the speed


def test_gamepad_rejects_bad_values():
    pad = GamepadMapping()
    with pytest.raises(ValueError, match="'left_x' is NaN"):
        pad.twist({"left_x": math.nan}, {})
    with pytest.raises(ValueError, match="unknown gamepad axes"):
        pad.twist({"throttle": 0.5}, {})
    with pytest.raises(ValueError, match="deadzone"):
        GamepadMapping(deadzone=1.0)


class XboxPadReading:
    """A frozen reading of a pygame joystick (the hardware is not available here)."""

    def __init__(self, axes, buttons):
        self.axes, self.buttons = axes, buttons

    def get_axis(self, i):
        return self.axes[i]

    def get_button(self, i):
        return self.buttons[i]


def test_pygame_joystick_reading_maps_triggers_to_unit_range():
    # axes: LX, LY, LT (resting -1), RX, RY, RT (fully pressed +1)
    reading = XboxPadReading([0.5, 0.0, -1.0, 0.0, 0.0, 1.0], [1, 0, 0, 0, 1, 0])
    axes, buttons = gamepad_state_from_joystick(reading)
    assert axes["left_trigger"] == 0.0 and axes["right_trigger"] == 1.0
    assert buttons["a"] and buttons["left_bumper"] and not buttons["right_bumper"]
    twist = GamepadMapping(linear_speed=1.0, angular_speed=1.0, deadzone=0.0).twist(axes, buttons)
    torch.testing.assert_close(twist, torch.tensor([0.5, 0.0, 1.0, 0.0, 0.0, -1.0], dtype=F64))


def test_command_frame_to_body_rotates_world_aligned_commands():
    rot = so3_exp(torch.tensor([math.pi, 0.0, 0.0], dtype=F64))  # EE pointing down
    world_down = torch.tensor([0.0, 0.0, -0.1, 0.0, 0.0, 0.3], dtype=F64)
    body = command_frame_to_body(world_down, rot)
    torch.testing.assert_close(body, torch.tensor([0.0, 0.0, 0.1, 0.0, 0.0, -0.3], dtype=F64))


def test_lerobot_keyboard_adapter():
    pytest.importorskip("lerobot.teleoperators.keyboard")
    # The action KeyboardTeleop.get_action() returns: {held key char: None}
    assert pressed_keys_from_keyboard_action(dict.fromkeys(["w", "i"], None)) == {"w", "i"}
    adapter = LeRobotKeyboardTwist(KeyboardMapping(linear_speed=0.1, angular_speed=0.5))
    adapter.connect()  # real LeRobot KeyboardTeleop; without a display pynput is not loaded
    if adapter.teleop.is_connected:  # pragma: no cover - only with a display
        assert adapter.twist().shape == (6,)
        adapter.disconnect()
    else:
        with pytest.raises(RuntimeError, match="not connected"):
            adapter.twist()
