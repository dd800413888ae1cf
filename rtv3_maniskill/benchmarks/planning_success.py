"""The planning benchmark's success rule (pose distance to a grasp's pre-grasp) and its per-step trace.

Poses are world-frame ``(4, 4)`` TCP transforms; the distance is the paper's pose distance with
the planning rotation weight 0.3/pi (m + (0.3/pi) rad, L1; docs/PAPER_DETAILS.md "Metrics"),
the smaller over the pre-grasp and its pi-about-z twin (parallel-jaw symmetry).
"""

from __future__ import annotations

import math

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


def trace_step(step: int, tcp_pose: torch.Tensor, grasp_pose: torch.Tensor, twist: torch.Tensor,
               distance: float, collision: bool) -> dict[str, float]:
    """One row of a trial trace: the TCP's translation (m) and rotation (deg) error to the grasp's
    pre-grasp (the nearer of it and its pi-about-z twin), the commanded speeds (m/s, rad/s), and
    how well the command points at that pre-grasp: the cosine of ``v`` and of ``w`` with the two
    halves of ``T_tcp^-1 T_pre`` (its translation and its rotation vector, TCP frame; +1 = straight
    at it, -1 = away). The rotation error splits into the angle between the two approach (z) axes
    and the roll about the approach (the twist part of a swing-twist split, deg); ``tcp_height`` is
    the TCP's world z (m, the table top is 0)."""
    # Imported here: importing rtv3_maniskill.tasks loads ManiSkill, which this pure module avoids.
    from rtv3_maniskill.tasks.grasp_sampler import canonicalize_symmetric

    tcp = tcp_pose.double()
    aimed = torch.from_numpy(canonicalize_symmetric(grasp_pose.double().numpy()[None], tcp.numpy())[0])
    to_target = se3.relative_transform(tcp, pregrasp_poses(aimed))  # the pre-grasp in the TCP frame
    straight = torch.cat([to_target[:3, 3], se3.so3_log(to_target[:3, :3])])
    command = twist.double().reshape(6)

    def cosine(a: torch.Tensor, b: torch.Tensor) -> float:
        return float(torch.dot(a, b) / (a.norm() * b.norm()).clamp_min(1e-12))

    quat = se3.matrix_to_quat(to_target[:3, :3])  # wxyz
    roll = 2.0 * math.atan2(float(quat[3]), float(quat[0]))
    roll = (roll + math.pi) % (2.0 * math.pi) - math.pi
    return dict(step=step, distance=distance, translation_error=float(straight[:3].norm()),
                rotation_error_deg=math.degrees(float(straight[3:].norm())),
                approach_error_deg=math.degrees(math.acos(max(-1.0, min(1.0, float(to_target[2, 2]))))),
                roll_error_deg=abs(math.degrees(roll)), tcp_height=float(tcp[2, 3]),
                linear_speed=float(command[:3].norm()), angular_speed=float(command[3:].norm()),
                linear_alignment=cosine(command[:3], straight[:3]), angular_alignment=cosine(command[3:], straight[3:]),
                collision=float(collision))
