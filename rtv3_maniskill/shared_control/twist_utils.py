"""Input checks and velocity limits shared by every controller in this package.

Twists are body-frame ``[v (m/s), w (rad/s)]`` of the current end-effector pose
(``rtv3_maniskill.se3`` conventions); poses are homogeneous ``(4, 4)`` matrices.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


def as_twist(value: Any, name: str = "user_twist", batch_size: int | None = None, dtype=torch.float64) -> torch.Tensor:
    """Validate a twist ``(6,)`` or ``(B, 6)`` and return it as a tensor of ``dtype``.

    Raises:
        ValueError: wrong shape (``batch_size`` given: ``(6,)`` or ``(batch_size, 6)``), or NaN/inf.
    """
    try:
        twist = torch.as_tensor(np.asarray(value) if not isinstance(value, torch.Tensor) else value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be an array of 6 numbers [v, w], got {type(value).__name__}") from err
    if not (twist.is_floating_point() or twist.dtype in (torch.int32, torch.int64)):
        raise ValueError(f"{name} must be a real-valued array, got dtype {twist.dtype}")
    twist = twist.to(dtype)
    ok_shapes = "(6,)" if batch_size is None else f"(6,) or ({batch_size}, 6)"
    if twist.ndim == 1:
        if twist.shape[0] != 6:
            raise ValueError(f"{name} must have shape {ok_shapes} ([v (3), w (3)]), got {tuple(twist.shape)}")
    elif twist.ndim == 2 and batch_size is not None:
        if twist.shape != (batch_size, 6):
            raise ValueError(f"{name} must have shape {ok_shapes} ([v (3), w (3)]), got {tuple(twist.shape)}")
    else:
        raise ValueError(f"{name} must have shape {ok_shapes} ([v (3), w (3)]), got {tuple(twist.shape)}")
    if not torch.isfinite(twist).all():
        raise ValueError(f"{name} contains NaN or inf: {twist.tolist()}")
    return twist


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
