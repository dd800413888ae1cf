"""The planning benchmark's success rule: pose distance to a grasp's pre-grasp.

Poses are world-frame ``(4, 4)`` TCP transforms; the distance is the paper's pose distance with
the planning rotation weight 0.3/pi (m + (0.3/pi) rad, L1; docs/PAPER_DETAILS.md "Metrics"),
the smaller over the pre-grasp and its pi-about-z twin (parallel-jaw symmetry).
"""

from __future__ import annotations

import torch

from rtv3_maniskill import se3
from rtv3_maniskill.features import pregrasp_poses

PLANNING_SUCCESS_THRESHOLD = 0.2
"""Pose distance (m + (0.3/pi) rad, L1) below which a pre-grasp counts as reached (docs/PAPER_DETAILS.md)."""


def planning_distance(tcp_pose: torch.Tensor, grasp_poses: torch.Tensor) -> torch.Tensor:
    """Distance ``(..., M)`` of the TCP ``(..., 4, 4)`` to each grasp's pre-grasp ``(..., M, 4, 4)``.

    The paper's pose distance with the planning rotation weight 0.3/pi, ``E = T_pre^-1 T_tcp``,
    the smaller of the pre-grasp and its pi-about-z twin (parallel-jaw symmetry).
    """
    if tcp_pose.shape[-2:] != (4, 4) or grasp_poses.ndim < 3 or grasp_poses.shape[-2:] != (4, 4):
        raise ValueError(
            f"need tcp_pose (..., 4, 4) and grasp_poses (..., M, 4, 4), "
            f"got {tuple(tcp_pose.shape)}, {tuple(grasp_poses.shape)}"
        )
    target = pregrasp_poses(grasp_poses)
    return se3.symmetric_pose_distance(target, tcp_pose[..., None, :, :].to(target.dtype), se3.PLANNING_ROT_WEIGHT)


def is_planning_success(distance: torch.Tensor | float, threshold: float = PLANNING_SUCCESS_THRESHOLD) -> torch.Tensor:
    """``distance < threshold`` (strict), elementwise."""
    return torch.as_tensor(distance) < threshold

