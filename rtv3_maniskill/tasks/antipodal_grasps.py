"""Antipodal parallel-jaw grasp candidates on one object (no hand collision check).

Steps 1-3 of the protocol in :mod:`rtv3_maniskill.tasks.grasp_sampler`: surface points with
face normals give approach directions (TCP z = -n), grasp depths and 6 yaws about the approach;
rays from both pad planes at the largest opening find the contacts (exact ray / convex-part
intersection in numpy); a grasp is kept when both contacts are on the object, the width is in
``[MIN_WIDTH, MAX_OPENING]``, each contact normal lies within the friction cone of the closing
axis, its score exceeds ``MIN_SCORE``, its TCP lies in the workspace cube (+ margin) and its
approach does not point up by more than ``max_approach_z``. The TCP is centred between the
contacts (the Panda's fingers close symmetrically).

Frames: world (z up, table top z = 0); poses world-from-TCP ``(4, 4)``; lengths in m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import coal
import numpy as np
import trimesh

from rtv3_maniskill.robot.panda_hand import FINGER_DEPTH, FINGERTIP_Z, MAX_OPENING, coal_convex
from rtv3_maniskill.robot.scene_geometry import WORKSPACE_CENTER, WORKSPACE_HALF_SIZE

MIN_WIDTH = 0.005
"""Narrowest grasp (m) between the contacts."""
MIN_SCORE = 0.4
"""Positive-label threshold (docs/PAPER_DETAILS.md, context)."""
FRICTION_COEFFICIENT = 0.5
"""Friction cone half-angle ``atan(mu)`` (26.6 deg) that each contact normal must lie within."""
NUM_YAWS = 6
"""Yaw angles over [0, pi) about the approach axis per surface point."""
DEPTH_RANGE = (-0.1, 1.1)
"""Grasp depth range in units of FINGER_DEPTH (VGN)."""
ALIGNMENT_WEIGHT = 0.8
"""Score = ``ALIGNMENT_WEIGHT * alignment + (1 - ALIGNMENT_WEIGHT) * room``."""
ROOM_SATURATION = 0.02
"""Spare opening (m, both sides together) at which the room term saturates at 1."""


@dataclass
class ConvexPart:
    """A convex object part in the world: half-spaces ``normals @ x <= offsets``."""

    normals: np.ndarray  # (P, 3)
    offsets: np.ndarray  # (P,)
    shape: coal.Convex
    sphere: np.ndarray  # (4,) centre + radius


def convex_part(mesh: trimesh.Trimesh) -> ConvexPart:
    """A convex world-frame mesh as half-spaces (duplicate planes merged), a coal shape and a bounding sphere."""
    normals = np.asarray(mesh.face_normals)
    offsets = np.einsum("ij,ij->i", normals, mesh.vertices[mesh.faces[:, 0]])
    # Coplanar triangles give the same plane; keep one of each.
    _, keep = np.unique(np.round(np.column_stack([normals, offsets]), 9), axis=0, return_index=True)
    keep = np.sort(keep)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre = (lo + hi) / 2
    radius = np.linalg.norm(mesh.vertices - centre, axis=1).max()
    return ConvexPart(
        normals[keep], offsets[keep], coal_convex(mesh.vertices, mesh.faces), np.append(centre, radius)
    )


def _first_entry(
    parts: list[ConvexPart], origins: np.ndarray, dirs: np.ndarray, max_t: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First entry of rays ``origins + t dirs`` (R, 3) into a union of convex parts.

    Returns ``t (R,)`` (inf where no entry in [0, max_t]), the entry face normal ``(R, 3)``
    and ``starts_inside (R,)``.
    """
    n_rays = len(origins)
    best_t = np.full(n_rays, np.inf)
    best_n = np.zeros((n_rays, 3))
    inside = np.zeros(n_rays, dtype=bool)
    for part in parts:
        denom = dirs @ part.normals.T  # (R, P)
        num = part.offsets[None] - origins @ part.normals.T  # inside where num >= t * denom
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / denom
        entering = denom < -1e-12
        exiting = denom > 1e-12
        parallel_out = (~entering & ~exiting & (num < 0)).any(1)
        t_in = np.where(entering, t, -np.inf)
        idx = t_in.argmax(1)
        t_enter = t_in[np.arange(n_rays), idx]
        t_exit = np.where(exiting, t, np.inf).min(1)
        crosses = ~parallel_out & (t_enter <= t_exit) & (t_exit > 0)
        inside |= crosses & (t_enter < 0)
        hit = crosses & (t_enter >= 0) & (t_enter <= max_t) & (t_enter < best_t)
        best_t = np.where(hit, t_enter, best_t)
        best_n[hit] = part.normals[idx[hit]]
    return best_t, best_n, inside


@dataclass
class Candidates:
    """Candidates of one object: ``poses (K, 4, 4)`` world-from-TCP, ``widths (K,)`` m, ``scores (K,)``."""

    poses: np.ndarray
    widths: np.ndarray
    scores: np.ndarray


def object_candidates(
    parts: list[ConvexPart],
    mesh: trimesh.Trimesh,
    part_of_face: np.ndarray,
    rng: np.random.Generator,
    num_samples: int,
    max_approach_z: float,
    workspace_margin: float,
) -> Candidates:
    """Antipodal, scored candidates on one object (no hand collision check yet).

    ``parts``: the object's convex parts (world frame); ``mesh``: their union, ``part_of_face`` the
    part of each of its faces; ``num_samples`` surface points, ``NUM_YAWS`` yaws each.
    """
    points, face_idx = trimesh.sample.sample_surface(mesh, num_samples, seed=rng)
    normals = np.asarray(mesh.face_normals)[face_idx]
    depth = rng.uniform(*DEPTH_RANGE, size=len(points)) * FINGER_DEPTH
    phase = rng.uniform(0.0, np.pi / NUM_YAWS, size=len(points))
    # Drop points buried inside another part of the same object (not on its outer surface).
    buried = np.zeros(len(points), dtype=bool)
    for k, part in enumerate(parts):
        if len(parts) > 1:
            inside = (points @ part.normals.T - part.offsets < -1e-3).all(1)
            buried |= inside & (part_of_face[face_idx] != k)
    keep = ~buried & (-normals[:, 2] <= max_approach_z)
    points, normals, depth, phase = points[keep], normals[keep], depth[keep], phase[keep]
    if len(points) == 0:
        return Candidates(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0))

    approach = -normals  # TCP z
    helper = np.where(np.abs(approach[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    base = np.cross(approach, helper)
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    other = np.cross(approach, base)
    yaws = phase[:, None] + np.arange(NUM_YAWS) * np.pi / NUM_YAWS  # (S, 6)
    closing = np.cos(yaws)[..., None] * base[:, None] + np.sin(yaws)[..., None] * other[:, None]
    z = np.broadcast_to(approach[:, None], closing.shape)
    tcp = points + (depth - FINGERTIP_Z)[:, None] * approach  # fingertips `depth` past the surface
    tcp = np.broadcast_to(tcp[:, None], closing.shape).reshape(-1, 3)
    y = closing.reshape(-1, 3)
    z = z.reshape(-1, 3)
    x = np.cross(y, z)

    half = MAX_OPENING / 2
    t_left, n_left, in_left = _first_entry(parts, tcp + half * y, -y, MAX_OPENING)
    t_right, n_right, in_right = _first_entry(parts, tcp - half * y, y, MAX_OPENING)
    with np.errstate(invalid="ignore"):
        width = MAX_OPENING - t_left - t_right  # nan/-inf where a ray missed
    cos_cone = 1.0 / math.sqrt(1.0 + FRICTION_COEFFICIENT**2)
    cos_left = np.einsum("ij,ij->i", n_left, y)
    cos_right = -np.einsum("ij,ij->i", n_right, y)
    ok = (
        np.isfinite(t_left)
        & np.isfinite(t_right)
        & ~in_left
        & ~in_right
        & (width >= MIN_WIDTH)
        & (width <= MAX_OPENING)
        & (cos_left >= cos_cone)
        & (cos_right >= cos_cone)
    )
    cone = math.acos(cos_cone)
    worst = np.arccos(np.clip(np.minimum(cos_left, cos_right), -1.0, 1.0))
    alignment = np.clip(1.0 - worst / cone, 0.0, 1.0)
    room = np.clip((MAX_OPENING - width) / ROOM_SATURATION, 0.0, 1.0)
    score = ALIGNMENT_WEIGHT * alignment + (1 - ALIGNMENT_WEIGHT) * room
    # Centre the TCP between the contacts.
    with np.errstate(invalid="ignore"):
        shift = np.where(ok, (t_right - t_left) / 2, 0.0)
    tcp = tcp + shift[:, None] * y
    lo = WORKSPACE_CENTER - WORKSPACE_HALF_SIZE - workspace_margin
    hi = WORKSPACE_CENTER + WORKSPACE_HALF_SIZE + workspace_margin
    ok &= (score > MIN_SCORE) & ((tcp >= lo) & (tcp <= hi)).all(1)
    idx = np.flatnonzero(ok)
    poses = np.zeros((len(idx), 4, 4))
    poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2] = x[idx], y[idx], z[idx]
    poses[:, :3, 3] = tcp[idx]
    poses[:, 3, 3] = 1.0
    return Candidates(poses, width[idx], score[idx])
