"""How the twist controllers execute a commanded twist (``--execution``)."""

from __future__ import annotations

EXECUTIONS: dict[str, dict[str, float]] = {
    "capped": dict(command_gain=1.0, max_linear_speed=0.3, max_angular_speed=1.2),
    "tracked": dict(command_gain=0.75, max_linear_speed=1.0, max_angular_speed=4.0),
}
"""How a commanded twist is executed: ``capped`` follows it up to 0.3 m/s and 1.2 rad/s; ``tracked``
is the authors' execution: the twist becomes a pose target one step ahead, tracked at gain 15,
so the arm moves 0.75 of the command per step, with no practical speed cap (1 m/s, 4 rad/s; the
joints' 2 rad/s still holds)."""
