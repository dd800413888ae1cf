"""Start configurations of the arm: the authors' demonstration start distribution around the ready pose."""

from __future__ import annotations

import numpy as np

from rtv3_maniskill.robot.scene_geometry import READY_QPOS

START_NOISE_STD = 0.6 * np.array([0.1, 0.04, 0.1, 0.04, 0.1, 0.1, 0.1])
"""Per-joint standard deviation of the start distribution, as a fraction of each joint's range
(docs/PAPER_DETAILS.md, "Authors' benchmark protocol")."""


def random_start_configuration(rng: np.random.Generator, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Arm joints ``(7,)`` from the authors' demonstration start distribution: the ready pose plus
    Gaussian noise of standard deviation ``START_NOISE_STD * (upper - lower)`` per joint, clipped to
    the joint limits ``lower``, ``upper`` ``(7,)`` (rad)."""
    lower, upper = np.asarray(lower, dtype=np.float64)[:7], np.asarray(upper, dtype=np.float64)[:7]
    q = READY_QPOS + rng.normal(size=7) * START_NOISE_STD * (upper - lower)
    return np.clip(q, lower, upper)
