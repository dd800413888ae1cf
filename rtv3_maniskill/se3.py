"""SE(3) / SO(3) math used everywhere in the project, batched in torch.

Conventions (the same as ManiSkill's ``Pose``):

* a pose is either a homogeneous matrix ``(..., 4, 4)`` or position ``(..., 3)`` +
  quaternion ``(..., 4)`` in **wxyz** order;
* a twist ``xi = [v, w]`` is ``(..., 6)``: translation velocity first, then rotation
  velocity (the paper's ``a = [v, w]``);
* ``T_{k+1} = T_k @ se3_exp(xi * dt)`` integrates a **body-frame** twist (paper, Sec. IV-D);
* ``se3_log(inv(T_a) @ T_b)`` is the body twist (times dt) that moves ``T_a`` onto ``T_b``.

All functions accept any leading batch shape, float32 or float64.
"""

from __future__ import annotations

import math

import torch

_EPS = 1e-6


def _skew_map() -> torch.Tensor:
    """Constant ``(3, 9)``: ``w @ map`` is the flattened ``[w]_x``."""
    m = torch.zeros(3, 9, dtype=torch.float64)
    for axis, (row, col), sign in ((2, (0, 1), -1), (1, (0, 2), 1), (2, (1, 0), 1), (0, (1, 2), -1), (1, (2, 0), -1),
                                   (0, (2, 1), 1)):
        m[axis, 3 * row + col] = sign
    return m


_SKEW = _skew_map()

_CONSTANTS: dict[tuple[int, torch.dtype, torch.device], torch.Tensor] = {}


def constant_like(table: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """The module-level constant ``table`` in ``like``'s dtype and device, converted once.

    Created outside inference mode, so a conversion first made in an inference call can
    still be saved for backward in a later training step.
    """
    key = (id(table), like.dtype, like.device)
    out = _CONSTANTS.get(key)
    if out is None:
        with torch.inference_mode(False):
            out = _CONSTANTS[key] = table.to(dtype=like.dtype, device=like.device)
    return out


def skew(w: torch.Tensor) -> torch.Tensor:
    """``(..., 3) -> (..., 3, 3)`` cross-product matrix ``[w]_x``."""
    return (w @ constant_like(_SKEW, w)).reshape(*w.shape[:-1], 3, 3)


def _so3_coefficients(theta: torch.Tensor, with_c: bool = True):
    """Series-safe ``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3`` (None
    unless ``with_c``)."""
    small = theta < 1e-4
    t = torch.where(small, 1.0, theta)
    theta_sq = theta * theta
    sin_t = torch.sin(t)
    a = torch.where(small, 1 - theta_sq / 6, sin_t / t)
    b = torch.where(small, 0.5 - theta_sq / 24, (1 - torch.cos(t)) / (t * t))
    c = torch.where(small, 1.0 / 6 - theta_sq / 120, (t - sin_t) / (t * t * t)) if with_c else None
    return a, b, c


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotation vector ``(..., 3)`` -> rotation matrix ``(..., 3, 3)``."""
    theta = w.norm(dim=-1)
    a, b, _ = _so3_coefficients(theta, with_c=False)
    k = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(rot: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(..., 3, 3)`` -> rotation vector ``(..., 3)`` with angle in [0, pi].

    Goes through the quaternion, which is numerically stable near 0 and near pi.
    """
    return quat_to_rotvec(matrix_to_quat(rot))


def _left_jacobian_inverse(w: torch.Tensor) -> torch.Tensor:
    """``V^{-1}`` of the SE(3) exponential for rotation vector ``w``: ``(..., 3, 3)``."""
    theta = w.norm(dim=-1)
    small = theta < 1e-4
    t = torch.where(small, torch.ones_like(theta), theta)
    half = t / 2
    coef = torch.where(small, 1.0 / 12 + theta**2 / 720, (1 - half * torch.cos(half) / torch.sin(half)) / (t * t))
    k = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye - 0.5 * k + coef[..., None, None] * (k @ k)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Twist ``(..., 6)`` ``[v, w]`` -> homogeneous matrix ``(..., 4, 4)``."""
    v, w = xi[..., :3], xi[..., 3:]
    theta = w.norm(dim=-1)
    a, b, c = _so3_coefficients(theta)
    k = skew(w)
    kk = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(k.shape)
    rot = eye + a[..., None, None] * k + b[..., None, None] * kk
    left_jac = eye + b[..., None, None] * k + c[..., None, None] * kk
    return make_transform(rot, (left_jac @ v[..., None])[..., 0])


def se3_log(transform: torch.Tensor) -> torch.Tensor:
    """Homogeneous matrix ``(..., 4, 4)`` -> twist ``(..., 6)`` ``[v, w]``."""
    w = so3_log(transform[..., :3, :3])
    v = (_left_jacobian_inverse(w) @ transform[..., :3, 3:4])[..., 0]
    return torch.cat([v, w], -1)


def make_transform(rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` rotation + ``(..., 3)`` translation -> ``(..., 4, 4)``."""
    out = torch.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
    out[..., :3, :3] = rot
    out[..., :3, 3] = trans
    out[..., 3, 3] = 1.0
    return out


def se3_inverse(transform: torch.Tensor) -> torch.Tensor:
    """Inverse of ``(..., 4, 4)`` rigid transforms."""
    rot_t = transform[..., :3, :3].transpose(-1, -2)
    return make_transform(rot_t, -(rot_t @ transform[..., :3, 3:4])[..., 0])


def relative_transform(reference: torch.Tensor, transform: torch.Tensor) -> torch.Tensor:
    """``inv(reference) @ transform``: ``transform`` expressed in the ``reference`` frame."""
    return se3_inverse(reference) @ transform


def adjoint(transform: torch.Tensor) -> torch.Tensor:
    """Adjoint ``(..., 6, 6)`` for ``[v, w]`` twists: ``xi_a = Ad(T_ab) xi_b``."""
    rot = transform[..., :3, :3]
    trans = transform[..., :3, 3]
    out = torch.zeros(*transform.shape[:-2], 6, 6, dtype=transform.dtype, device=transform.device)
    out[..., :3, :3] = rot
    out[..., 3:, 3:] = rot
    out[..., :3, 3:] = skew(trans) @ rot
    return out


def body_twist(transform_from: torch.Tensor, transform_to: torch.Tensor, dt: float) -> torch.Tensor:
    """Constant body twist ``(..., 6)`` that moves ``transform_from`` to ``transform_to`` in ``dt`` s."""
    return se3_log(relative_transform(transform_from, transform_to)) / dt


def integrate_body_twists(start: torch.Tensor, twists: torch.Tensor, dt: float) -> torch.Tensor:
    """Poses ``(..., H, 4, 4)`` reached by applying twists ``(..., H, 6)`` from ``start (..., 4, 4)``.

    ``T_t = T_{t-1} Exp(a_t dt)`` (paper, Sec. IV-D).
    """
    steps = se3_exp(twists * dt)
    poses = []
    current = start
    for t in range(twists.shape[-2]):
        current = current @ steps[..., t, :, :]
        poses.append(current)
    return torch.stack(poses, -3)


# --------------------------------------------------------------------------- quaternions


def _quat_matrix_map() -> torch.Tensor:
    """Constant ``(16, 9)``: the flattened outer product ``q q^T`` (wxyz) times it is the rotation
    matrix of a unit quaternion (homogeneous form, e.g. ``R00 = ww + xx - yy - zz``)."""
    w, x, y, z = range(4)
    entries = [
        [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)], [(x, y, 2), (w, z, -2)], [(x, z, 2), (w, y, 2)],
        [(x, y, 2), (w, z, 2)], [(w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)], [(y, z, 2), (w, x, -2)],
        [(x, z, 2), (w, y, -2)], [(y, z, 2), (w, x, 2)], [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
    ]
    m = torch.zeros(16, 9, dtype=torch.float64)
    for out, terms in enumerate(entries):
        for a, b, coef in terms:
            m[4 * a + b, out] += coef
    return m


_QUAT_MATRIX = _quat_matrix_map()


def quat_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(..., 4)`` wxyz -> rotation matrix ``(..., 3, 3)``."""
    quat = quat / quat.norm(dim=-1, keepdim=True)
    outer = (quat[..., :, None] * quat[..., None, :]).reshape(*quat.shape[:-1], 16)
    return (outer @ constant_like(_QUAT_MATRIX, quat)).reshape(*quat.shape[:-1], 3, 3)


def _linear_map(rows: list[dict[str, float]]) -> torch.Tensor:
    """Constant ``(R, 10)`` map from ``[1, m00, m01, ..., m22]`` (a flattened 3x3 plus a one) to R outputs."""
    keys = ["1"] + [f"m{i}{j}" for i in range(3) for j in range(3)]
    return torch.tensor([[row.get(k, 0.0) for k in keys] for row in rows], dtype=torch.float64)


# Shepperd's method: four candidate (unnormalised) quaternions wxyz, each well conditioned when
# its "diagonal" entry below is the largest; written as one linear map of the matrix entries.
_QUAT_CANDIDATES = _linear_map([
    {"1": 1, "m00": 1, "m11": 1, "m22": 1}, {"m21": 1, "m12": -1}, {"m02": 1, "m20": -1}, {"m10": 1, "m01": -1},
    {"m21": 1, "m12": -1}, {"1": 1, "m00": 1, "m11": -1, "m22": -1}, {"m01": 1, "m10": 1}, {"m02": 1, "m20": 1},
    {"m02": 1, "m20": -1}, {"m01": 1, "m10": 1}, {"1": 1, "m00": -1, "m11": 1, "m22": -1}, {"m12": 1, "m21": 1},
    {"m10": 1, "m01": -1}, {"m02": 1, "m20": 1}, {"m12": 1, "m21": 1}, {"1": 1, "m00": -1, "m11": -1, "m22": 1},
])
_QUAT_PIVOTS = _linear_map([{"m00": 1, "m11": 1, "m22": 1}, {"m00": 1}, {"m11": 1}, {"m22": 1}])
_QUAT_MAPS_T = torch.cat([_QUAT_CANDIDATES, _QUAT_PIVOTS]).T.contiguous()
"""``(10, 20)``: ``[1, m00 .. m22] @ _QUAT_MAPS_T`` = the 4 candidates x 4, then the 4 pivots."""


def matrix_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(..., 3, 3)`` -> unit quaternion ``(..., 4)`` wxyz with ``w >= 0``."""
    lead = rot.shape[:-2]
    entries = torch.cat([torch.ones(*lead, 1, dtype=rot.dtype, device=rot.device), rot.reshape(*lead, 9)], -1)
    # (..., 20): 4 candidates x 4, then the 4 pivots [trace, m00, m11, m22]
    out = entries @ constant_like(_QUAT_MAPS_T, rot)
    cands = out[..., :16].reshape(*lead, 4, 4)
    best = out[..., 16:].argmax(-1)
    quat = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    quat = quat / quat.norm(dim=-1, keepdim=True)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def quat_to_rotvec(quat: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(..., 4)`` wxyz -> rotation vector ``(..., 3)`` (angle in [0, pi])."""
    quat = torch.where(quat[..., :1] < 0, -quat, quat)
    xyz = quat[..., 1:]
    sin_half = xyz.norm(dim=-1)
    angle = 2 * torch.atan2(sin_half, quat[..., 0])
    scale = torch.where(sin_half < _EPS, 2.0 / quat[..., 0].clamp_min(_EPS), angle / sin_half.clamp_min(_EPS))
    return xyz * scale[..., None]


def pose_to_matrix(position: torch.Tensor, quat_wxyz: torch.Tensor) -> torch.Tensor:
    """ManiSkill pose ``p (..., 3)``, ``q (..., 4)`` wxyz -> ``(..., 4, 4)``."""
    return make_transform(quat_to_matrix(quat_wxyz), position)


def matrix_to_pose(transform: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` -> ``(..., 7)`` position + wxyz quaternion."""
    return torch.cat([transform[..., :3, 3], matrix_to_quat(transform[..., :3, :3])], -1)


# --------------------------------------------------------------------------- metrics


def matrix_to_euler_xyz(rot: torch.Tensor) -> torch.Tensor:
    """Extrinsic x-y-z Euler angles ``(..., 3)`` (``R = Rz(c) Ry(b) Rx(a)``)."""
    sy = (-rot[..., 2, 0]).clamp(-1.0, 1.0)
    b = torch.asin(sy)
    a = torch.atan2(rot[..., 2, 1], rot[..., 2, 2])
    c = torch.atan2(rot[..., 1, 0], rot[..., 0, 0])
    return torch.stack([a, b, c], -1)


PLANNING_ROT_WEIGHT = 0.3 / math.pi
"""Rotation weight of the trajectory/planning pose distance (docs/PAPER_DETAILS.md, metrics)."""
SHARED_CONTROL_ROT_WEIGHT = 0.6 / math.pi
"""Rotation weight of the shared-control success distance (docs/PAPER_DETAILS.md, metrics)."""


def pose_distance(
    transform_ref: torch.Tensor, transform: torch.Tensor, rot_weight: float = PLANNING_ROT_WEIGHT
) -> torch.Tensor:
    """The paper's manifold distance ``(...)`` between poses ``(..., 4, 4)`` (appendix, Distance Metric).

    ``E = inv(T_ref) T``; ``d = ||t_E||_1 + rot_weight * ||euler_xyz(E)||_1``. Units: m and rad.
    """
    err = relative_transform(transform_ref, transform)
    return err[..., :3, 3].abs().sum(-1) + rot_weight * matrix_to_euler_xyz(err[..., :3, :3]).abs().sum(-1)


def translate_along_z(transform: torch.Tensor, distance: float) -> torch.Tensor:
    """Move ``(..., 4, 4)`` poses by ``distance`` along their own z axis (``T @ Trans(0, 0, d)``);
    a grasp's pre-grasp is ``translate_along_z(grasp, -0.05)``."""
    out = transform.clone()
    out[..., :3, 3] = transform[..., :3, 3] + distance * transform[..., :3, 2]
    return out


def symmetric_pose_distance(target: torch.Tensor, pose: torch.Tensor, rot_weight: float) -> torch.Tensor:
    """:func:`pose_distance` to ``target`` or its pi-about-z twin, whichever is smaller
    (a parallel-jaw grasp and its twin are the same grasp)."""
    d = pose_distance(target, pose, rot_weight)
    return torch.minimum(d, pose_distance(rotate_about_z(target, math.pi), pose, rot_weight))


_HALF_TURN_Z = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64)
"""Column signs of ``T @ Rz(pi)`` for a ``(4, 4)`` transform."""


def rotate_about_z(transform: torch.Tensor, angle: float) -> torch.Tensor:
    """Right-multiply ``(..., 4, 4)`` by a rotation of ``angle`` about the local z axis.

    ``angle == math.pi`` (a parallel-jaw grasp's twin) is exact: the x and y axes change sign.
    """
    if angle == math.pi:
        return transform * constant_like(_HALF_TURN_Z, transform)
    rz = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]],
        dtype=transform.dtype,
        device=transform.device,
    )
    out = transform.clone()
    out[..., :3, :3] = transform[..., :3, :3] @ rz
    return out
