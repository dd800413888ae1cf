"""Antipodal parallel-jaw grasp candidates for a clutter scene (``GraspClutter-v1``).

Protocol (docs/PAPER_DETAILS.md "Scene generation", VGN/GIGA sampling plus a geometric antipodal
test instead of a simulated lift):

1. per object, sample surface points with face normals on its collision mesh (world
   frame); approach along the inward normal (TCP z = -n); grasp depth
   ``d ~ U(-0.1, 1.1) * FINGER_DEPTH`` = how far the fingertips pass the surface point;
   6 yaw angles over [0, pi) about the approach axis (random phase per point);
2. antipodal test: rays from both pad planes at the largest opening (0.08 m) towards the
   TCP along ∓y, exact ray / convex-part intersection in numpy; two contacts on the
   object, width in [MIN_WIDTH, MAX_OPENING], each contact normal within the friction
   cone (mu = 0.5, 26.6 deg) of the closing axis; the TCP is then moved along y to the
   contacts' midpoint (the Panda's fingers close symmetrically);
3. score = 0.8 * alignment + 0.2 * room, alignment = 1 - (worst normal angle / cone
   angle) (1 = perfectly antipodal), room = spare opening beyond the width, saturating at
   1 cm per side; only score > MIN_SCORE (0.4, the positive label) is kept;
4. reject TCPs outside the workspace cube (+ margin) and approaches pointing upward by
   more than ``max_approach_z`` (the wrist and forearm would have to pass below the
   TCP, towards the table); reject hands (palm, wrist flange, fingers opened to
   width + clearance, all swept back to the pre-grasp) that touch any object or the
   table, and grasps with another object inside the closing region (coal);
5. canonicalise the parallel-jaw symmetry against the robot's rest TCP orientation;
   pick up to ``max_grasps`` round-robin over objects by descending score with
   per-object non-maximum suppression (1.5 cm / 20 deg); hand collisions are checked
   lazily, only for grasps about to be picked.

Frames: world (z up, table top z = 0); grasp poses are world-from-TCP ``(4, 4)`` in the
``panda_hand_tcp`` convention (see :mod:`rtv3_maniskill.robot.panda_hand`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import coal
import numpy as np
import torch
import trimesh

from rtv3_maniskill.features import PREGRASP_DISTANCE
from rtv3_maniskill.robot.panda_hand import (
    CLOSING_REGION_CENTER,
    FINGER_DEPTH,
    FINGERTIP_Z,
    MAX_OPENING,
    PandaHandCollisionModel,
    closing_region_size,
    coal_convex,
)
from rtv3_maniskill.robot.scene_geometry import WORKSPACE_CENTER, WORKSPACE_HALF_SIZE, SceneGeometry
from rtv3_maniskill.se3 import matrix_to_quat, rotate_about_z, translate_along_z

MIN_WIDTH = 0.005
MIN_SCORE = 0.4
"""Positive-label threshold (docs/PAPER_DETAILS.md, context)."""
FRICTION_COEFFICIENT = 0.5
NUM_YAWS = 6
DEPTH_RANGE = (-0.1, 1.1)
"""Grasp depth range in units of FINGER_DEPTH (VGN)."""
REST_TCP_ROTATION = np.diag([1.0, -1.0, -1.0])
"""World rotation of the Panda's TCP at ManiSkill's ``rest`` keyframe (base at the world
origin's orientation): pointing down, x away from the robot. Reference for canonicalising."""
ALIGNMENT_WEIGHT = 0.8
ROOM_SATURATION = 0.02


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


def canonicalize_symmetric(grasp_poses: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Of each grasp and its copy rotated by pi about its z axis (same parallel-jaw grasp),
    return the one closer in orientation to ``reference (4, 4)``. ``grasp_poses (M, 4, 4)``.

    ``tr(R_ref^T R Rz(pi)) = -x_ref.x - y_ref.y + z_ref.z``, so the flip is closer exactly
    when ``x_ref.x + y_ref.y < 0`` (ties keep the input).
    """
    poses = np.asarray(grasp_poses, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"grasp_poses must be (M, 4, 4), got {poses.shape}")
    if reference.shape != (4, 4):
        raise ValueError(f"reference must be (4, 4), got {reference.shape}")
    if not (np.isfinite(poses).all() and np.isfinite(reference).all()):
        raise ValueError("grasp_poses and reference must be finite (found NaN/inf)")
    closeness = np.einsum("i,mi->m", reference[:3, 0], poses[:, :3, 0]) + np.einsum(
        "i,mi->m", reference[:3, 1], poses[:, :3, 1]
    )
    flip = closeness < 0
    out = poses.copy()
    if flip.any():
        out[flip] = rotate_about_z(torch.from_numpy(poses[flip]), math.pi).numpy()
    return out


# --------------------------------------------------------------------------- geometry


@dataclass
class _ConvexPart:
    """A convex object part in the world: half-spaces ``normals @ x <= offsets``."""

    normals: np.ndarray  # (P, 3)
    offsets: np.ndarray  # (P,)
    shape: coal.Convex
    sphere: np.ndarray  # (4,) centre + radius


def _convex_part(mesh: trimesh.Trimesh) -> _ConvexPart:
    normals = np.asarray(mesh.face_normals)
    offsets = np.einsum("ij,ij->i", normals, mesh.vertices[mesh.faces[:, 0]])
    # Coplanar triangles give the same plane; keep one of each.
    _, keep = np.unique(np.round(np.column_stack([normals, offsets]), 9), axis=0, return_index=True)
    keep = np.sort(keep)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre = (lo + hi) / 2
    radius = np.linalg.norm(mesh.vertices - centre, axis=1).max()
    return _ConvexPart(
        normals[keep], offsets[keep], coal_convex(mesh.vertices, mesh.faces), np.append(centre, radius)
    )


def _first_entry(
    parts: list[_ConvexPart], origins: np.ndarray, dirs: np.ndarray, max_t: float
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


def _rotation_angle_symmetric(rot_a: np.ndarray, rots: np.ndarray) -> np.ndarray:
    """Angle (rad) between ``rot_a (3, 3)`` and each of ``rots (K, 3, 3)``, modulo the jaw flip."""
    d = np.einsum("ij,kij->k", rot_a[:, :2], rots[:, :, :2])  # x.x' + y.y'
    dz = np.einsum("i,ki->k", rot_a[:, 2], rots[:, :, 2])
    trace = np.maximum(d + dz, -d + dz)
    return np.arccos(np.clip((trace - 1) / 2, -1.0, 1.0))


@dataclass
class _Candidates:
    poses: np.ndarray
    widths: np.ndarray
    scores: np.ndarray


def _object_candidates(
    parts: list[_ConvexPart],
    mesh: trimesh.Trimesh,
    part_of_face: np.ndarray,
    rng: np.random.Generator,
    num_samples: int,
    max_approach_z: float,
    workspace_margin: float,
    reference: np.ndarray,
) -> _Candidates:
    """Antipodal, scored, canonical candidates on one object (no hand collision check yet)."""
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
        return _Candidates(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0))

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
    poses = canonicalize_symmetric(poses, reference)
    return _Candidates(poses, width[idx], score[idx])


def sample_grasps(
    scene: SceneGeometry,
    rng: np.random.Generator,
    max_grasps: int = 64,
    num_surface_samples: int = 192,
    finger_clearance: float = 0.01,
    approach_distance: float = PREGRASP_DISTANCE,
    max_approach_z: float = 0.5,
    workspace_margin: float = 0.03,
    nms_distance: float = 0.015,
    nms_angle: float = math.radians(20.0),
    reference: np.ndarray | None = None,
    hand: PandaHandCollisionModel | None = None,
) -> GraspSet:
    """Collision-free antipodal grasps (score > 0.4) spread over the scene's objects.

    ``num_surface_samples`` surface points per object, 6 yaws each. The hand is checked
    with its fingers opened to ``min(width + 2 * finger_clearance, MAX_OPENING)`` and
    swept back by ``approach_distance`` (pre-grasp to grasp). ``max_approach_z``: largest
    world z component of the approach direction (0.5 = 30 deg above horizontal).
    ``reference (4, 4)``: orientation for the jaw-flip canonicalisation (default: the
    robot's rest TCP orientation). Deterministic given ``rng``.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if int(max_grasps) != max_grasps or max_grasps <= 0:
        raise ValueError(f"max_grasps must be a positive integer, got {max_grasps}")
    if int(num_surface_samples) != num_surface_samples or num_surface_samples <= 0:
        raise ValueError(f"num_surface_samples must be a positive integer, got {num_surface_samples}")
    for name, value in (
        ("finger_clearance", finger_clearance),
        ("approach_distance", approach_distance),
        ("workspace_margin", workspace_margin),
        ("nms_distance", nms_distance),
        ("nms_angle", nms_angle),
    ):
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {value}")
    n_obj = len(scene.objects)
    object_poses = np.asarray(scene.object_poses, dtype=np.float64)
    if n_obj == 0:
        return GraspSet.empty()
    if object_poses.shape != (n_obj, 4, 4):
        raise ValueError(f"scene.object_poses must be ({n_obj}, 4, 4) for {n_obj} objects, got {object_poses.shape}")
    if not np.isfinite(object_poses).all():
        raise ValueError("scene.object_poses contains NaN/inf")
    reference = np.diag([*REST_TCP_ROTATION.diagonal(), 1.0]) if reference is None else np.asarray(reference, float)
    if reference.shape != (4, 4):
        raise ValueError(f"reference must be (4, 4), got {reference.shape}")
    if hand is None:
        hand = _default_hand(float(approach_distance))

    # World-frame convex parts of every object.
    object_parts: list[list[_ConvexPart]] = []
    candidates: list[_Candidates] = []
    for obj, pose in zip(scene.objects, object_poses):
        meshes = [shape.to_trimesh() for shape in obj.shapes]
        for m in meshes:
            m.apply_transform(pose)
        parts = [_convex_part(m) for m in meshes]
        object_parts.append(parts)
        merged = trimesh.util.concatenate(meshes)  # = obj.collision_mesh() in the world frame
        part_of_face = np.repeat(np.arange(len(meshes)), [len(m.faces) for m in meshes])
        candidates.append(
            _object_candidates(
                parts, merged, part_of_face, rng, int(num_surface_samples), max_approach_z, workspace_margin, reference
            )
        )

    table_top = float(scene.table_center[2] + scene.table_half_size[2])
    all_shapes = [p.shape for parts in object_parts for p in parts]
    all_spheres = np.array([p.sphere for parts in object_parts for p in parts]).reshape(-1, 4)
    owner = np.repeat(np.arange(n_obj), [len(parts) for parts in object_parts])

    # Per object: sort by score, drop hands below the table (vectorised, exact for a half-space).
    order: list[np.ndarray] = []
    openings: list[np.ndarray] = []
    for c in candidates:
        opening = np.minimum(c.widths + 2 * finger_clearance, MAX_OPENING)
        above = np.ones(len(c.widths), dtype=bool)
        if len(c.widths):
            verts = hand.part_vertices_world(c.poses, opening)
            above = verts[..., 2].min(1) >= table_top + hand.security_margin
        idx = np.flatnonzero(above)
        order.append(idx[np.argsort(-c.scores[idx], kind="stable")])
        openings.append(opening)

    def admissible(i: int, j: int) -> bool:
        pose, opening = candidates[i].poses[j], openings[i][j]
        if hand.collides(pose, opening, all_shapes, all_spheres):
            return False
        others = np.flatnonzero(owner != i)
        if others.size == 0:
            return True
        region = coal.Box(*closing_region_size(opening))
        tf = coal.Transform3s(pose[:3, :3], pose[:3, :3] @ CLOSING_REGION_CENTER + pose[:3, 3])
        req = coal.CollisionRequest()
        res = coal.CollisionResult()
        for k in others:
            centre, radius = all_spheres[k, :3], all_spheres[k, 3]
            if np.linalg.norm(pose[:3, 3] - centre) > radius + MAX_OPENING:
                continue
            res.clear()
            if coal.collide(region, tf, all_shapes[k], coal.Transform3s(), req, res):
                return False
        return True

    selected: list[tuple[int, int]] = []
    chosen: list[list[int]] = [[] for _ in range(n_obj)]
    cursor = [0] * n_obj

    def next_valid(i: int) -> int | None:
        c = candidates[i]
        while cursor[i] < len(order[i]):
            j = int(order[i][cursor[i]])
            cursor[i] += 1
            if chosen[i]:
                prev = np.array(chosen[i])
                near = np.linalg.norm(c.poses[prev, :3, 3] - c.poses[j, :3, 3], axis=1) < nms_distance
                if near.any() and (
                    _rotation_angle_symmetric(c.poses[j, :3, :3], c.poses[prev[near], :3, :3]) < nms_angle
                ).any():
                    continue
            if admissible(i, j):
                return j
        return None

    while len(selected) < max_grasps:
        round_picks = [(i, j) for i in range(n_obj) if (j := next_valid(i)) is not None]
        if not round_picks:
            break
        round_picks.sort(key=lambda ij: -candidates[ij[0]].scores[ij[1]])
        for i, j in round_picks:
            if len(selected) < max_grasps:
                selected.append((i, j))
                chosen[i].append(j)

    if not selected:
        return GraspSet.empty()
    return GraspSet(
        poses=np.stack([candidates[i].poses[j] for i, j in selected]),
        widths=np.array([candidates[i].widths[j] for i, j in selected]),
        scores=np.array([candidates[i].scores[j] for i, j in selected]),
        object_ids=np.array([i for i, _ in selected], dtype=np.int64),
    )


_HANDS: dict[float, PandaHandCollisionModel] = {}


def _default_hand(approach_distance: float) -> PandaHandCollisionModel:
    if approach_distance not in _HANDS:
        _HANDS[approach_distance] = PandaHandCollisionModel(approach_sweep=approach_distance)
    return _HANDS[approach_distance]
