"""What the motion planner returns: a time-parameterized joint trajectory and a plan's outcome.

Joint vectors are the Panda's ``(7,)`` arm joints in radians; times in seconds from the
trajectory's start, on the 20 Hz control grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from rtv3_maniskill.robot.panda_model import DOF

FailureReason = Literal["ik_failed", "start_in_collision", "goal_in_collision", "planning_failed", "timeout"]
FAILURE_REASONS: tuple[str, ...] = ("ik_failed", "start_in_collision", "goal_in_collision", "planning_failed",
                                    "timeout")


@dataclass
class JointTrajectory:
    """A time-parameterized arm trajectory sampled at the control rate.

    ``q`` ``(S, 7)`` joint positions (rad), ``qd`` ``(S, 7)`` joint velocities (rad/s),
    ``t`` ``(S,)`` times (s) from 0 in steps of ``dt``. The last sample is the goal,
    at rest.
    """

    q: np.ndarray
    qd: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        self.q = np.asarray(self.q, dtype=np.float64)
        self.qd = np.asarray(self.qd, dtype=np.float64)
        self.t = np.asarray(self.t, dtype=np.float64)
        if self.q.ndim != 2 or self.q.shape[1] != DOF:
            raise ValueError(f"q must be (S, 7), got {self.q.shape}")
        if self.qd.shape != self.q.shape:
            raise ValueError(f"qd must match q's shape {self.q.shape}, got {self.qd.shape}")
        if self.t.shape != (self.q.shape[0],):
            raise ValueError(f"t must be ({self.q.shape[0]},), got {self.t.shape}")
        if not (np.isfinite(self.q).all() and np.isfinite(self.qd).all() and np.isfinite(self.t).all()):
            raise ValueError("trajectory contains NaN or inf")

    @property
    def duration(self) -> float:
        """Time of the last sample (s)."""
        return float(self.t[-1]) if len(self.t) else 0.0

    def __len__(self) -> int:
        return self.q.shape[0]

    def concatenate(self, other: JointTrajectory) -> JointTrajectory:
        """This trajectory followed by ``other``, which must start where this one ends.

        ``other``'s first sample (a duplicate of this one's last) is dropped and its
        times are shifted so the result stays on the same ``dt`` grid.
        """
        if np.abs(other.q[0] - self.q[-1]).max() > 1e-3:
            raise ValueError("other trajectory does not start at this trajectory's last configuration")
        return JointTrajectory(
            q=np.concatenate([self.q, other.q[1:]]),
            qd=np.concatenate([self.qd, other.qd[1:]]),
            t=np.concatenate([self.t, self.t[-1] + other.t[1:] - other.t[0]]),
        )


@dataclass
class PlanResult:
    """Outcome of a planning call.

    ``trajectory`` is set iff ``success``; otherwise ``failure_reason`` is one of
    ``FAILURE_REASONS``. ``goal_q`` ``(7,)`` is the reached configuration,
    ``waypoints`` ``(K, 7)`` the simplified geometric path, ``planning_time`` in s.
    """

    success: bool
    trajectory: JointTrajectory | None = None
    failure_reason: FailureReason | None = None
    message: str = ""
    goal_q: np.ndarray | None = None
    waypoints: np.ndarray | None = None
    planning_time: float = 0.0

    def __post_init__(self) -> None:
        if self.success != (self.trajectory is not None):
            raise ValueError("a PlanResult has a trajectory iff it succeeded")
        if not self.success and self.failure_reason not in FAILURE_REASONS:
            raise ValueError(f"failure_reason must be one of {FAILURE_REASONS}, got {self.failure_reason!r}")
