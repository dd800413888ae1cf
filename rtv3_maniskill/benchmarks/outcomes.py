"""How a trial ends: the first of a robot contact (collision), the target reached (success), or the
step limit (timeout); what a colliding robot touched."""

from __future__ import annotations

from typing import Any

OUTCOMES = ("success", "collision", "timeout")
CONTACT_KINDS = ("table", "object", "self")
"""What a ``collision`` trial's robot touched (``contact`` column, "+"-joined when several)."""


def describe_contact(base: Any) -> str:
    """What the robot of sub-scene 0 of ``base`` (a ``GraspClutterEnv``) touches now, "+"-joined in
    ``CONTACT_KINDS`` order (``""``: nothing)."""
    kinds = base.robot_contact_kinds()[0]
    return "+".join(kind for kind in CONTACT_KINDS if kind in kinds)


def trial_outcome(collision: bool, success: bool) -> str | None:
    """Outcome decided at one step: a contact fails the trial even if the pose was reached; None = go on."""
    if collision:
        return "collision"
    if success:
        return "success"
    return None
