"""The grasp candidates of one scene: world-frame TCP poses, opening widths, scores and objects.

Poses are world-from-TCP ``(4, 4)`` in the ``panda_hand_tcp`` convention (z = approach axis,
y = finger closing axis; see :mod:`rtv3_maniskill.robot.panda_hand`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from rtv3_maniskill.features import PREGRASP_DISTANCE
from rtv3_maniskill.se3 import matrix_to_quat, translate_along_z


@dataclass
class GraspSet:
    """Grasp candidates of one scene.

    ``poses (M, 4, 4)`` world-from-TCP; ``widths (M,)`` m, opening at the contacts;
    ``scores (M,)`` in [0, 1]; ``object_ids (M,)`` int64 index into ``scene.objects``.
    """

    poses: np.ndarray
    widths: np.ndarray
    scores: np.ndarray
    object_ids: np.ndarray

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        self.widths = np.asarray(self.widths, dtype=np.float64).reshape(-1)
        self.scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        self.object_ids = np.asarray(self.object_ids, dtype=np.int64).reshape(-1)
        m = len(self.poses)
        for name in ("widths", "scores", "object_ids"):
            if len(getattr(self, name)) != m:
                raise ValueError(f"GraspSet.{name} has {len(getattr(self, name))} entries, poses has {m}")

    def __len__(self) -> int:
        return len(self.poses)

    @classmethod
    def empty(cls) -> GraspSet:
        return cls(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))

    def pregrasp_poses(self, distance: float = PREGRASP_DISTANCE) -> np.ndarray:
        """``(M, 4, 4)`` poses moved back by ``distance`` (m) along their approach axis (-z)."""
        if not np.isfinite(distance):
            raise ValueError(f"distance must be finite, got {distance}")
        return translate_along_z(torch.from_numpy(self.poses), -distance).numpy()

    def to_padded(self, max_grasps: int) -> tuple[np.ndarray, np.ndarray]:
        """``((max_grasps, 9) float32 [pos (3), quat wxyz (4), width, score], (max_grasps,) mask)``
        in the layout of ``features.GRASPS``; padding rows are zeros with mask 0."""
        if int(max_grasps) <= 0:
            raise ValueError(f"max_grasps must be positive, got {max_grasps}")
        if len(self) > max_grasps:
            raise ValueError(f"max_grasps={max_grasps} is smaller than the {len(self)} grasps in the set")
        rows = np.zeros((max_grasps, 9), dtype=np.float32)
        mask = np.zeros(max_grasps, dtype=np.float32)
        m = len(self)
        if m:
            quat = matrix_to_quat(torch.from_numpy(self.poses[:, :3, :3])).numpy()
            rows[:m, :3] = self.poses[:, :3, 3]
            rows[:m, 3:7] = quat
            rows[:m, 7] = self.widths
            rows[:m, 8] = self.scores
            mask[:m] = 1.0
        return rows, mask
