"""Simulated users for the shared-control benchmark (paper appendix "Simulated User"; docs/PAPER_DETAILS.md).

Every user aims at a goal pose (the target grasp's pre-grasp) and computes the ideal
command ``e = se3_log(T_cur^-1 T_goal)``: the body twist (EE frame, ``[v (m/s), w (rad/s)]``)
that reaches the goal in one second. It is unscaled, as in docs/PAPER_DETAILS.md and the appendix (no
gain). The appendix writes ``Logmap(T_goal T_cur^-1)`` but calls it the twist "in the local
frame"; the body twist ``T_cur^-1 T_goal`` (docs/PAPER_DETAILS.md) is the one that is local, and the one
the controllers here execute. An optional norm clip (``max_linear_speed`` /
``max_angular_speed``) is applied to the final command.

Users (``make_user(name, seed)``):

* ``ideal``: ``e`` (a noiseless user; reference only).
* ``noisy``: ``e + N(0, 0.05 I6)``; 0.05 is the *variance* (docs/PAPER_DETAILS.md).
* ``laggy``: with probability 0.8 repeat the previous command, else ``e``.
* ``mode_switching``: 20 steps translation only ``[v, 0]``, then 20 steps rotation only ``[0, w]``.
* ``single_dof``: every 10 steps pick ``i* = argmax_i |e_i| w_i`` (``w`` = 1 for translation,
  0.1 for rotation: docs/PAPER_DETAILS.md/authors' code; the appendix gives the unweighted argmax) and
  command ``2 e_i*`` on that DoF alone (gain 2: docs/PAPER_DETAILS.md; the appendix writes ``e_i``). The
  DoF is held for the period, its value recomputed each step from the current ``e``.
* ``low_dof``: translation only ``[v, 0]``.

:class:`IntermittentUser` wraps any of them into a user who pauses (commands for a number of
steps, then gives no command for a number of steps: the paper's motivation for asynchronous
autonomy); ``make_user(name, seed, pauses=(command_steps, rest_steps))`` builds one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from rtv3_maniskill.se3 import relative_transform, se3_log
from rtv3_maniskill.shared_control.twist_utils import as_pose, check_speed_limits, clamp_twist_speed


class SimulatedUser:
    """Base class: goal-driven user giving a body twist ``(6,)`` float64 each step.

    Args:
        seed: seed of the user's ``numpy.random.Generator`` (ignored if ``rng`` is given).
        rng: a generator to use instead.
        max_linear_speed, max_angular_speed: optional norm clips (m/s, rad/s) of the command.
    """

    name = "ideal"

    def __init__(
        self,
        seed: int | None = None,
        rng: np.random.Generator | None = None,
        max_linear_speed: float | None = None,
        max_angular_speed: float | None = None,
    ) -> None:
        check_speed_limits(max_linear_speed, max_angular_speed)
        self.rng = rng if rng is not None else np.random.default_rng(seed)
        self.max_linear_speed = max_linear_speed
        self.max_angular_speed = max_angular_speed
        self.goal_pose: torch.Tensor | None = None
        self.step_count = 0

    def reset(self, goal_pose: Any) -> None:
        """New episode towards ``goal_pose`` ``(4, 4)`` (world)."""
        self.goal_pose = as_pose(goal_pose, "goal_pose")
        self.step_count = 0
        self._reset_state()

    def _reset_state(self) -> None:
        """Subclass hook: clear per-episode state."""

    def error(self, ee_pose: Any) -> torch.Tensor:
        """Ideal command ``e = se3_log(T_cur^-1 T_goal)`` ``(6,)`` for the current EE pose ``(4, 4)`` (world)."""
        if self.goal_pose is None:
            raise RuntimeError(f"{type(self).__name__}: call reset(goal_pose) before using the user")
        return se3_log(relative_transform(as_pose(ee_pose), self.goal_pose))

    def _command(self, e: torch.Tensor) -> torch.Tensor:
        """Subclass hook: the command before clipping, from ``e``."""
        return e

    def __call__(self, ee_pose: Any) -> torch.Tensor:
        """Command ``(6,)`` float64 body twist for the current EE pose ``(4, 4)``."""
        command = self._command(self.error(ee_pose))
        self.step_count += 1
        return clamp_twist_speed(command, self.max_linear_speed, self.max_angular_speed)


class IdealUser(SimulatedUser):
    """Noiseless user: ``u = e``."""

    name = "ideal"


class NoisyUser(SimulatedUser):
    """``u = e + N(0, variance I6)``, variance 0.05 (docs/PAPER_DETAILS.md)."""

    name = "noisy"

    def __init__(self, seed: int | None = None, variance: float = 0.05, **kwargs: Any) -> None:
        super().__init__(seed, **kwargs)
        if not variance >= 0:
            raise ValueError(f"variance must be >= 0, got {variance}")
        self.variance = variance

    def _command(self, e: torch.Tensor) -> torch.Tensor:
        noise = self.rng.normal(0.0, np.sqrt(self.variance), size=6)
        return e + torch.from_numpy(noise)


class LaggyUser(SimulatedUser):
    """With probability ``repeat_probability`` (0.8) repeat the previous command, else send ``e``."""

    name = "laggy"

    def __init__(self, seed: int | None = None, repeat_probability: float = 0.8, **kwargs: Any) -> None:
        super().__init__(seed, **kwargs)
        if not 0.0 <= repeat_probability <= 1.0:
            raise ValueError(f"repeat_probability must be in [0, 1], got {repeat_probability}")
        self.repeat_probability = repeat_probability
        self._previous: torch.Tensor | None = None

    def _reset_state(self) -> None:
        self._previous = None

    def __call__(self, ee_pose: Any) -> torch.Tensor:
        e = self.error(ee_pose)  # validates the pose even when the command is repeated
        repeat = self._previous is not None and self.rng.random() < self.repeat_probability
        command = (self._previous.clone() if repeat
                   else clamp_twist_speed(e, self.max_linear_speed, self.max_angular_speed))
        self._previous = command
        self.step_count += 1
        return command.clone()


class ModeSwitchingUser(SimulatedUser):
    """``period`` (20) steps translation only, then ``period`` steps rotation only, repeating."""

    name = "mode_switching"

    def __init__(self, seed: int | None = None, period: int = 20, **kwargs: Any) -> None:
        super().__init__(seed, **kwargs)
        if period < 1:
            raise ValueError(f"period must be >= 1, got {period}")
        self.period = period

    @property
    def translation_mode(self) -> bool:
        """True while the next command is translation only."""
        return (self.step_count // self.period) % 2 == 0

    def _command(self, e: torch.Tensor) -> torch.Tensor:
        out = torch.zeros_like(e)
        block = slice(0, 3) if self.translation_mode else slice(3, 6)
        out[block] = e[block]
        return out


class SingleDoFUser(SimulatedUser):
    """Every ``period`` (10) steps choose the DoF with the largest weighted ``|e_i|``; command ``gain * e_i``."""

    name = "single_dof"

    def __init__(
        self, seed: int | None = None, period: int = 10, gain: float = 2.0, rotation_weight: float = 0.1, **kwargs: Any
    ) -> None:
        super().__init__(seed, **kwargs)
        if period < 1 or rotation_weight < 0:
            raise ValueError(f"period must be >= 1 and rotation_weight >= 0, got {period}, {rotation_weight}")
        self.period = period
        self.gain = gain
        self.rotation_weight = rotation_weight
        self.active_dof: int | None = None

    def _reset_state(self) -> None:
        self.active_dof = None

    def _command(self, e: torch.Tensor) -> torch.Tensor:
        if self.step_count % self.period == 0 or self.active_dof is None:
            weights = torch.tensor([1.0, 1.0, 1.0] + [self.rotation_weight] * 3, dtype=e.dtype)
            self.active_dof = int((e.abs() * weights).argmax())
        out = torch.zeros_like(e)
        out[self.active_dof] = self.gain * e[self.active_dof]
        return out


class LowDoFUser(SimulatedUser):
    """Translation only: ``u = [v, 0]``."""

    name = "low_dof"

    def _command(self, e: torch.Tensor) -> torch.Tensor:
        out = torch.zeros_like(e)
        out[:3] = e[:3]
        return out


USERS: dict[str, Callable[..., SimulatedUser]] = {
    cls.name: cls for cls in (IdealUser, NoisyUser, LaggyUser, ModeSwitchingUser, SingleDoFUser, LowDoFUser)
}
"""Registry: user name -> class."""


class IntermittentUser:
    """A user who pauses: ``command_steps`` steps of ``inner``'s commands, then ``rest_steps``
    steps of no command (a zero twist), repeated. ``inner`` is not called while resting, so its
    own clock (mode-switching or single-DoF periods, lag) pauses too.

    Args:
        inner: the simulated user that gives the commands.
        command_steps: steps of each commanding phase (>= 1).
        rest_steps: steps of each pause (>= 0; 0 = never pauses).
    """

    def __init__(self, inner: SimulatedUser, command_steps: int, rest_steps: int) -> None:
        if int(command_steps) < 1 or int(rest_steps) < 0:
            raise ValueError(f"pauses need command_steps >= 1 and rest_steps >= 0, got {command_steps}, {rest_steps}")
        self.inner = inner
        self.command_steps, self.rest_steps = int(command_steps), int(rest_steps)
        self.name = f"{inner.name}+pauses"
        self.step_count = 0

    def reset(self, goal_pose: Any) -> None:
        self.inner.reset(goal_pose)
        self.step_count = 0

    @property
    def resting(self) -> bool:
        """True when the next call gives no command."""
        return self.step_count % (self.command_steps + self.rest_steps) >= self.command_steps

    def __call__(self, ee_pose: Any) -> torch.Tensor:
        command = torch.zeros(6, dtype=torch.float64) if self.resting else self.inner(ee_pose)
        self.step_count += 1
        return command


def make_user(name: str, seed: int | None = None, pauses: tuple[int, int] | None = None,
              **kwargs: Any) -> SimulatedUser | IntermittentUser:
    """Build a simulated user by name (``-`` and ``_`` and case are interchangeable).

    ``pauses=(command_steps, rest_steps)`` wraps it in an :class:`IntermittentUser`.

    Raises:
        ValueError: unknown name (the message lists the known ones), or bad ``pauses``.
    """
    key = str(name).strip().lower().replace("-", "_")
    if key not in USERS:
        raise ValueError(f"unknown simulated user {name!r}; known users: {', '.join(sorted(USERS))}")
    user = USERS[key](seed=seed, **kwargs)
    if pauses is None:
        return user
    if len(pauses) != 2:
        raise ValueError(f"pauses must be (command_steps, rest_steps), got {pauses!r}")
    return IntermittentUser(user, *pauses)
