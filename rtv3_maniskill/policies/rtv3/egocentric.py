"""Egocentric representation (paper Sec. IV and appendix): every input in the current EE frame.

With ``T_0`` the current end-effector pose (world frame), a world-frame quantity ``X`` enters
the network as ``T_0^-1 X``. Applying one rigid transform ``G`` to every world-frame input
(``T -> G T``, ``P -> G P``, ``G_i -> G G_i``) leaves all of these unchanged, which is the
paper's SE(3)-equivariance argument. Body twists are frame-invariant already.

All outputs here are in SI units (m, rad, m/s, rad/s); network scaling happens in the model.
"""

from __future__ import annotations

import math

import torch

from rtv3_maniskill import features, se3


def state_poses(states: torch.Tensor) -> torch.Tensor:
    """``(..., 27)`` observation.state -> EE poses ``(..., 4, 4)`` in the world frame."""
    return se3.pose_to_matrix(states[..., features.EE_POS], states[..., features.EE_QUAT])


def uniform_se3_noise(like: torch.Tensor, first: float, last: float) -> torch.Tensor:
    """``(..., 6)`` samples of ``U(-[first]*3, [first]*3) x U(-[last]*3, [last]*3)`` with ``like``'s
    leading shape, dtype and device (``like`` is ``(..., 6)``)."""
    bound = like.new_tensor([first] * 3 + [last] * 3)
    return (torch.rand_like(like) * 2 - 1) * bound


def perturb_poses(poses: torch.Tensor, translation: float, rotation: float) -> torch.Tensor:
    """Right-multiply ``(..., 4, 4)`` poses by ``Exp(u)``, ``u ~ U(-[t]*3, [t]*3) x U(-[r]*3, [r]*3)``.

    Training augmentation (docs/PAPER_DETAILS.md: uniform se(3) noise on the inputs).
    """
    like = poses.new_empty(*poses.shape[:-2], 6)
    return poses @ se3.se3_exp(uniform_se3_noise(like, translation, rotation))


def perturb_twists(twists: torch.Tensor, linear: float, angular: float) -> torch.Tensor:
    """Add ``U(-[l]*3, [l]*3) x U(-[a]*3, [a]*3)`` noise to body twists ``(..., 6)`` [v m/s, w rad/s].

    Training augmentation of the history's twists (``RTV3Config.twist_noise_*``).
    """
    return twists + uniform_se3_noise(twists, linear, angular)


def resample_past_rotation(
    poses: torch.Tensor, twists: torch.Tensor, selected: torch.Tensor, max_rate: float, dt: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace the past turn of ``selected`` samples by a random constant one, so that their past turn
    says nothing about where the turn goes next.

    Training augmentation against continuing the past rotation (``RTV3Config.history_rotation_resample_prob``):
    the targets stay the expert's turn toward the goal, so the rotation head has to read the goal. The
    new turn has one rate ``w ~ U(-max_rate, max_rate)^3`` rad/s (body frame), ``R'_t = R_0 Exp(w t dt)``
    for ``t = -T+1 .. 0``: it ends at the current orientation. Positions and world-frame linear
    velocities are kept (the body-frame ``v`` is re-expressed in the new orientations).

    Args:
        poses: ``(B, T, 4, 4)`` world EE poses, the last one current.
        twists: ``(B, T, 6)`` body twists of those poses (m/s, rad/s).
        selected: ``(B,)`` bool, which samples to change.
        max_rate: bound of each rate component (rad/s). dt: control period (s).
    Returns:
        ``(poses, twists)`` with the same shapes; unselected samples unchanged.
    """
    batch, steps = poses.shape[:2]
    current = poses[:, -1:, :3, :3]
    rate = (torch.rand(batch, 3, dtype=poses.dtype, device=poses.device) * 2 - 1) * max_rate
    times = torch.arange(1 - steps, 1, dtype=poses.dtype, device=poses.device) * dt  # (T,) <= 0
    rotation = current @ se3.so3_exp(rate[:, None, :] * times[None, :, None])  # (B, T, 3, 3)
    angular = rate[:, None, :].expand(-1, steps, -1)
    linear_world = (poses[..., :3, :3] @ twists[..., :3, None].to(poses.dtype))[..., 0]
    linear = (rotation.transpose(-1, -2) @ linear_world[..., None])[..., 0]
    new_twists = torch.cat([linear, angular], -1).to(twists.dtype)
    new_poses = poses.clone()
    new_poses[..., :3, :3] = rotation
    pick = selected[:, None]
    return (torch.where(pick[..., None, None], new_poses, poses), torch.where(pick[..., None], new_twists, twists))


def history_dynamics(
    relative: torch.Tensor, body_twists: torch.Tensor, log_relative: torch.Tensor | None = None
) -> torch.Tensor:
    """Past dynamics ``x_t = [log(T_0^-1 T_t), Ad(T_0^-1 T_t) xi_t]`` (paper, Dynamics Encoding).

    Args:
        relative: ``(B, T, 4, 4)`` past poses in the current EE frame, ``T_0^-1 T_t`` (last = identity).
        body_twists: ``(B, T, 6)`` EE body twists ``xi_t`` (each in its own frame ``T_t``).
        log_relative: ``se3_log(relative)`` if already computed (batched with other logs).
    Returns:
        ``(B, T, 12)``: pose relative to the current EE frame (6, log map) and the twist expressed
        in the current EE frame (6).
    """
    if log_relative is None:
        log_relative = se3.se3_log(relative)
    return torch.cat([log_relative, (se3.adjoint(relative) @ body_twists[..., None])[..., 0]], -1)


def future_dynamics(actions: torch.Tensor, dt: float) -> torch.Tensor:
    """Future dynamics ``x_{1:H}`` from the action window alone (training only, for h+).

    ``T_0^-1 T_t = prod_{k<t} Exp(a_k dt)`` (actions are realised body twists, ``features.ACTION``);
    the twist of step ``t`` is ``a_{t-1}``, expressed in the current frame with the adjoint.

    Args:
        actions: ``(B, H, 6)`` body twists ``a_0 .. a_{H-1}`` (m/s, rad/s).
    Returns:
        ``(B, H, 12)`` ``[log(T_0^-1 T_t), Ad(T_0^-1 T_t) a_{t-1}]`` for ``t = 1 .. H``.
    """
    eye = torch.eye(4, dtype=actions.dtype, device=actions.device).expand(actions.shape[0], 4, 4)
    relative = se3.integrate_body_twists(eye, actions, dt)
    return torch.cat([se3.se3_log(relative), (se3.adjoint(relative) @ actions[..., None])[..., 0]], -1)


def points_in_frame(frame: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
    """World points ``(B, N, 3)`` -> coordinates in ``frame (B, 4, 4)``: ``R^T (p - t)``."""
    rot, trans = frame[:, None, :3, :3], frame[:, None, :3, 3]
    return ((xyz - trans)[..., None, :] @ rot)[..., 0, :]


_IDENTITY_QUAT = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)


def grasps_in_frame(frame: torch.Tensor, grasps: torch.Tensor) -> torch.Tensor:
    """Grasp poses relative to ``frame``: ``(B, M, 9)`` grasps -> ``(B, M, 4, 4)`` ``T_0^-1 G``.

    Parallel-jaw symmetry (docs/PAPER_DETAILS.md): ``G`` and ``G Rz(pi)`` are the same grasp; the one whose
    orientation is closer to the current EE orientation is kept (larger rotation trace, i.e.
    ``R_00 + R_11 >= 0`` after the choice). Padded rows (zero quaternion) give the identity
    rotation and are masked by the caller.
    """
    quat = grasps[..., 3:7]
    safe_quat = torch.where(quat.norm(dim=-1, keepdim=True) > 1e-8, quat, se3.constant_like(_IDENTITY_QUAT, quat))
    relative = se3.relative_transform(frame[:, None], se3.pose_to_matrix(grasps[..., 0:3], safe_quat))
    flipped = se3.rotate_about_z(relative, math.pi)
    flip = (relative[..., 0, 0] + relative[..., 1, 1]) < 0
    return torch.where(flip[..., None, None], flipped, relative)
