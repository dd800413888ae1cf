"""Input checks and velocity limits shared by every controller in this package.

Twists are body-frame ``[v (m/s), w (rad/s)]`` of the current end-effector pose
(``rtv3_maniskill.se3`` conventions); poses are homogeneous ``(4, 4)`` matrices.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from rtv3_maniskill import features, se3


def as_pose(value: Any, name: str = "ee_pose", dtype=torch.float64) -> torch.Tensor:
    """Validate one homogeneous pose ``(4, 4)`` (finite, rotation block orthonormal)."""
    pose = torch.as_tensor(np.asarray(value) if not isinstance(value, torch.Tensor) else value).to(dtype)
    if pose.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) homogeneous matrix, got shape {tuple(pose.shape)}")
    if not torch.isfinite(pose).all():
        raise ValueError(f"{name} contains NaN or inf")
    rot = pose[:3, :3]
    if (rot.T @ rot - torch.eye(3, dtype=dtype)).abs().max() > 1e-3:
        raise ValueError(f"{name} has a rotation block that is not orthonormal")
    return pose


def as_poses(value: Any, name: str = "goals", dtype=torch.float64) -> torch.Tensor:
    """Validate a stack of poses ``(G, 4, 4)``, G >= 1."""
    poses = torch.as_tensor(np.asarray(value) if not isinstance(value, torch.Tensor) else value).to(dtype)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (G, 4, 4), got {tuple(poses.shape)}")
    if poses.shape[0] == 0:
        raise ValueError(f"{name} is empty: at least one goal pose is needed")
    if not torch.isfinite(poses).all():
        raise ValueError(f"{name} contains NaN or inf")
    return poses


def clamp_twist_speed(
    twist: torch.Tensor, max_linear_speed: float | None, max_angular_speed: float | None
) -> torch.Tensor:
    """Scale ``v`` and ``w`` of ``(..., 6)`` twists down so ``||v|| <= max_linear_speed`` and
    ``||w|| <= max_angular_speed`` (direction kept). ``None`` = no limit."""
    out = twist.clone()
    for sl, limit in ((slice(0, 3), max_linear_speed), (slice(3, 6), max_angular_speed)):
        if limit is None:
            continue
        norm = out[..., sl].norm(dim=-1, keepdim=True)
        scale = torch.where(norm > limit, limit / norm.clamp_min(1e-12), torch.ones_like(norm))
        out[..., sl] = out[..., sl] * scale
    return out


def check_speed_limits(max_linear_speed: float | None, max_angular_speed: float | None) -> None:
    """Raise ``ValueError`` for a non-positive or non-finite limit."""
    for name, value in (("max_linear_speed", max_linear_speed), ("max_angular_speed", max_angular_speed)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number or None, got {value}")


def step_inputs(observation: Mapping[str, Any], user_twist: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Check one control step's inputs, once, at the edge of an assistance method.

    Args:
        observation: feature dict (``rtv3_maniskill.features``) with ``observation.state (B, 27)``.
        user_twist: ``(B, 6)`` user body twist ``[v (m/s), w (rad/s)]`` (TCP frame), or None for
            "no input" (zeros).
    Returns:
        ``state (B, 27)`` and ``user (B, 6)``, both float32.
    Raises:
        ValueError: a missing state, a wrong shape or dtype, or NaN/inf, named in the message.
    """
    if not isinstance(observation, Mapping):
        raise ValueError(f"observation must be a dict of features, got {type(observation).__name__}")
    if features.STATE not in observation:
        raise ValueError(f"observation lacks {features.STATE!r} (B, {features.STATE_DIM}) (needed for the TCP pose)")
    state = _as_float_tensor(observation[features.STATE], features.STATE)
    if state.ndim != 2 or state.shape[1] != features.STATE_DIM:
        raise ValueError(f"{features.STATE} must be batched (B, {features.STATE_DIM}), got {tuple(state.shape)}")
    if not torch.isfinite(state).all():
        raise ValueError(f"{features.STATE} contains NaN or inf")
    b = state.shape[0]
    if user_twist is None:
        return state, torch.zeros(b, 6, dtype=torch.float32, device=state.device)
    user = _as_float_tensor(user_twist, "user_twist")
    if tuple(user.shape) != (b, 6):
        raise ValueError(f"user_twist must have shape ({b}, 6) ([v (3), w (3)] per batch element), "
                         f"got {tuple(user.shape)}")
    if not torch.isfinite(user).all():
        raise ValueError(f"user_twist contains NaN or inf: {user.tolist()}")
    return state, user.to(state.device)


def _as_float_tensor(value: Any, name: str) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        tensor = value
    elif isinstance(value, np.ndarray):
        tensor = torch.from_numpy(value)
    else:
        raise ValueError(f"{name} must be a torch tensor or numpy array, got {type(value).__name__}")
    if not tensor.is_floating_point():
        raise ValueError(f"{name} must be a floating-point array, got dtype {tensor.dtype}")
    return tensor.float()


def tcp_poses(state: torch.Tensor) -> torch.Tensor:
    """``(B, 4, 4)`` float64 TCP poses (world) from ``observation.state (B, 27)``."""
    state = state.double()
    return se3.pose_to_matrix(state[:, features.EE_POS], state[:, features.EE_QUAT])


def pregrasp_goals(grasps: torch.Tensor, grasps_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The pre-grasps of one scene's valid grasps, each with its pi-about-z twin (parallel jaws).

    Args:
        grasps: ``(M, 9)`` ``observation.grasps`` of one batch element (world).
        grasps_mask: ``(M,)``.
    Returns:
        ``goals (2G, 4, 4)`` float64 (world) and ``groups (2G,)`` the grasp index of each (a
        pre-grasp and its twin form one goal).
    Raises:
        ValueError: no valid grasp.
    """
    index = torch.nonzero(grasps_mask > 0.5).flatten()
    if len(index) == 0:
        raise ValueError("the scene has no valid grasp candidate: at least one goal is needed")
    rows = grasps[index].double()
    pre = features.pregrasp_poses(se3.pose_to_matrix(rows[:, :3], rows[:, 3:7]))
    return torch.cat([pre, se3.rotate_about_z(pre, math.pi)]), torch.cat([index, index])
