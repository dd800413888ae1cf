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

Steps 1-3 and the workspace and approach filters of step 4 run per object in
:mod:`rtv3_maniskill.tasks.antipodal_grasps`; this module checks the hand, canonicalises and
selects, and returns a :class:`~rtv3_maniskill.tasks.grasp_set.GraspSet`.

Frames: world (z up, table top z = 0); grasp poses are world-from-TCP ``(4, 4)`` in the
``panda_hand_tcp`` convention (see :mod:`rtv3_maniskill.robot.panda_hand`).
"""

from __future__ import annotations

import math

import coal
import numpy as np
import torch
import trimesh

from rtv3_maniskill.features import PREGRASP_DISTANCE
from rtv3_maniskill.robot.panda_hand import (
    CLOSING_REGION_CENTER,
    MAX_OPENING,
    PandaHandCollisionModel,
    closing_region_size,
)
from rtv3_maniskill.robot.scene_geometry import SceneGeometry
from rtv3_maniskill.se3 import rotate_about_z
from rtv3_maniskill.tasks.antipodal_grasps import Candidates, ConvexPart, convex_part, object_candidates
from rtv3_maniskill.tasks.grasp_set import GraspSet

REST_TCP_ROTATION = np.diag([1.0, -1.0, -1.0])
"""World rotation of the Panda's TCP at ManiSkill's ``rest`` keyframe (base at the world
origin's orientation): pointing down, x away from the robot. Reference for canonicalising."""


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


def _rotation_angle_symmetric(rot_a: np.ndarray, rots: np.ndarray) -> np.ndarray:
    """Angle (rad) between ``rot_a (3, 3)`` and each of ``rots (K, 3, 3)``, modulo the jaw flip."""
    d = np.einsum("ij,kij->k", rot_a[:, :2], rots[:, :, :2])  # x.x' + y.y'
    dz = np.einsum("i,ki->k", rot_a[:, 2], rots[:, :, 2])
    trace = np.maximum(d + dz, -d + dz)
    return np.arccos(np.clip((trace - 1) / 2, -1.0, 1.0))


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
    object_parts: list[list[ConvexPart]] = []
    candidates: list[Candidates] = []
    for obj, pose in zip(scene.objects, object_poses):
        meshes = [shape.to_trimesh() for shape in obj.shapes]
        for m in meshes:
            m.apply_transform(pose)
        parts = [convex_part(m) for m in meshes]
        object_parts.append(parts)
        merged = trimesh.util.concatenate(meshes)  # = obj.collision_mesh() in the world frame
        part_of_face = np.repeat(np.arange(len(meshes)), [len(m.faces) for m in meshes])
        found = object_candidates(parts, merged, part_of_face, rng, int(num_surface_samples), max_approach_z,
                                  workspace_margin)
        candidates.append(Candidates(canonicalize_symmetric(found.poses, reference), found.widths, found.scores))

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
