"""Collision model of the Panda hand (palm, wrist flange, two fingers) in the TCP frame.

TCP frame (ManiSkill's ``panda_hand_tcp`` link, checked against ``panda_v2.urdf`` of
mani-skill 3.0.1 and ``Panda.build_grasp_pose``):

* origin between the two fingertip pads: ``panda_hand_tcp_joint`` is a pure offset of
  ``TCP_OFFSET = 0.1034`` m along the hand's z axis; the pad links
  (``panda_*finger_pad``) sit at z = +0.5 mm and y = ±q in this frame (q = one finger's
  joint value), so the pads meet at the origin when closed;
* **z = approach direction** (out of the palm towards the object);
* **y = closing axis**: ``panda_finger_joint1`` (left finger) is prismatic along +y,
  ``panda_finger_joint2`` along -y (mimic), each in [0, 0.04] m, so the opening is
  ``2 q <= MAX_OPENING = 0.08`` m;
* x = y × z (``build_grasp_pose`` stacks ``[closing × approaching, closing, approaching]``
  as the columns of the rotation).

Geometry in the TCP frame (all from the URDF's collision elements, measured with trimesh):

* palm: convex hull of ``meshes/collision/hand.stl`` (already convex: hull volume equals
  mesh volume), extents x ±0.0316, y -0.1040..0.1004, z -0.1293..-0.0374 m (the palm's
  face is 3.74 cm behind the TCP);
* wrist flange: convex hull of ``link7.stl`` (rigidly attached to the hand:
  ``panda_joint8`` z 0.107, ``panda_hand_joint`` yaw -pi/4), z -0.158..-0.104 m;
* each finger: convex hull of its four URDF boxes (screw mount, sledge, diagonal, rubber
  tip); the finger frame sits at z = 0.0584 - 0.1034 = -0.045 m, y = ±q. The rubber tip
  covers z -0.0090..+0.0095 m (tip 9.5 mm beyond the TCP), |x| <= 8.75 mm and its inner
  face lies on the plane y = ±q. The hull never reaches inside that pad plane, so it
  only adds volume outside the jaw gap;
* fingers reach 4.7 cm beyond the palm face: ``FINGER_DEPTH = 0.05`` m (the value VGN
  uses for the Panda) is the depth range unit of the grasp sampler.

Every part is made symmetric under a rotation by pi about z (hull of the part and its
rotated copy; only the wrist flange and the palm's 3.6 mm y-asymmetry change), so a
collision verdict holds for both parallel-jaw variants of a grasp. Parts can be swept
back along -z (``approach_sweep``) to cover the straight approach from the pre-grasp.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Literal

import coal
import numpy as np
import trimesh

TCP_OFFSET = 0.1034
"""``panda_hand`` -> ``panda_hand_tcp`` offset along the hand's z axis (m)."""
FINGER_JOINT_Z = 0.0584
"""z of both finger joint origins in the ``panda_hand`` frame (m)."""
FINGER_Z_IN_TCP = FINGER_JOINT_Z - TCP_OFFSET
MAX_OPENING = 0.08
"""Largest distance between the finger pads (2 x 0.04 m joint limit)."""
FINGER_DEPTH = 0.05
"""Grasp depth unit (m): fingers reach 4.7 cm beyond the palm; VGN uses 0.05 for the Panda."""
FINGERTIP_Z = 0.0095
"""z of the fingertips in the TCP frame (m): 0.0584 + 0.04525 + 0.00925 - 0.1034."""
PAD_HALF_X = 0.00875
"""Half width of the rubber pad across the jaw (TCP x, m)."""
PAD_Z_RANGE = (-0.0090, 0.0095)
"""z extent of the rubber pad in the TCP frame (m)."""
LINK7_IN_HAND_Z = -0.107
LINK7_IN_HAND_YAW = np.pi / 4

# Left finger collision boxes in the left finger frame (panda_v2.urdf):
# (centre xyz, roll about x, full size xyz). The right finger mirrors y and roll.
LEFT_FINGER_BOXES: tuple[tuple[tuple[float, float, float], float, tuple[float, float, float]], ...] = (
    ((0.0, 18.5e-3, 11e-3), 0.0, (22e-3, 15e-3, 20e-3)),  # screw mount
    ((0.0, 6.8e-3, 2.2e-3), 0.0, (22e-3, 8.8e-3, 3.8e-3)),  # carriage sledge
    ((0.0, 15.9e-3, 28.35e-3), np.pi / 6, (17.5e-3, 7e-3, 23.5e-3)),  # diagonal finger
    ((0.0, 7.58e-3, 45.25e-3), 0.0, (17.5e-3, 15.2e-3, 18.5e-3)),  # rubber tip
)

PartKind = Literal["hand", "left_finger", "right_finger"]
_FLIP = np.diag([-1.0, -1.0, 1.0])


def panda_asset_dir() -> Path:
    """Folder of ManiSkill's Panda assets (found without importing mani_skill)."""
    spec = importlib.util.find_spec("mani_skill")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("mani_skill is not installed; the Panda hand meshes come with it")
    return Path(list(spec.submodule_search_locations)[0]) / "assets" / "robots" / "panda"


def _box_vertices(center, roll: float, size) -> np.ndarray:
    """``(8, 3)`` corners of a box rotated by ``roll`` about x, then moved to ``center``."""
    half = np.asarray(size) / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    c, s = np.cos(roll), np.sin(roll)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return corners @ rot.T + np.asarray(center)


def _transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


@dataclass(frozen=True, eq=False)
class HandPart:
    """One convex part. ``vertices (V, 3)`` / ``faces (F, 3)`` in the TCP frame at zero
    opening; finger parts move by ``±opening / 2`` along TCP y (``kind``)."""

    name: str
    kind: PartKind
    vertices: np.ndarray
    faces: np.ndarray

    def offset(self, openings: np.ndarray) -> np.ndarray:
        """``(M, 3)`` translation in the TCP frame for finger ``openings (M,)``."""
        openings = np.asarray(openings, dtype=float)
        out = np.zeros((*openings.shape, 3))
        if self.kind == "left_finger":
            out[..., 1] = openings / 2
        elif self.kind == "right_finger":
            out[..., 1] = -openings / 2
        return out


def _hull_part(name: str, kind: PartKind, points: np.ndarray, sweep: float, symmetric: bool) -> HandPart:
    pts = np.asarray(points, dtype=float)
    if symmetric:
        pts = np.concatenate([pts, pts @ _FLIP.T])
    if sweep > 0:
        pts = np.concatenate([pts, pts - np.array([0.0, 0.0, sweep])])
    hull = trimesh.convex.convex_hull(pts)
    return HandPart(name, kind, np.asarray(hull.vertices), np.asarray(hull.faces))


@lru_cache(maxsize=8)
def hand_parts(approach_sweep: float = 0.0, include_wrist: bool = True) -> tuple[HandPart, ...]:
    """Convex parts of the hand in the TCP frame at zero opening.

    ``approach_sweep`` (m) extends every part back along -z by that distance, so the parts
    cover the straight-line approach from a pre-grasp ``approach_sweep`` behind the grasp.
    """
    if approach_sweep < 0:
        raise ValueError(f"approach_sweep must be >= 0, got {approach_sweep}")
    meshes = panda_asset_dir() / "franka_description" / "meshes" / "collision"
    tcp_from_hand = np.eye(4)
    tcp_from_hand[2, 3] = -TCP_OFFSET
    palm = trimesh.load(meshes / "hand.stl", force="mesh")
    parts = [_hull_part("palm", "hand", _transform_points(tcp_from_hand, palm.vertices), approach_sweep, True)]
    if include_wrist:
        # inverse of panda_joint8 (z 0.107) followed by panda_hand_joint (yaw -pi/4)
        hand_from_link7 = trimesh.transformations.rotation_matrix(LINK7_IN_HAND_YAW, [0, 0, 1])
        hand_from_link7 = hand_from_link7 @ trimesh.transformations.translation_matrix([0, 0, LINK7_IN_HAND_Z])
        link7 = trimesh.load(meshes / "link7.stl", force="mesh")
        verts = _transform_points(tcp_from_hand @ hand_from_link7, link7.vertices)
        parts.append(_hull_part("wrist", "hand", verts, approach_sweep, True))
    left = np.concatenate([_box_vertices(*box) for box in LEFT_FINGER_BOXES])
    left[:, 2] += FINGER_Z_IN_TCP
    right = left * np.array([1.0, -1.0, 1.0])
    parts.append(_hull_part("left_finger", "left_finger", left, approach_sweep, False))
    parts.append(_hull_part("right_finger", "right_finger", right, approach_sweep, False))
    return tuple(parts)


CLOSING_REGION_CENTER = np.array([0.0, 0.0, (PAD_Z_RANGE[0] + PAD_Z_RANGE[1]) / 2])
"""Centre (TCP frame) of the box swept by the pads when the jaw closes."""


def closing_region_size(opening: float) -> tuple[float, float, float]:
    """Full size ``(x, y, z)`` of the box swept by the pads when closing from ``opening`` (m)."""
    return (2 * PAD_HALF_X, float(opening), PAD_Z_RANGE[1] - PAD_Z_RANGE[0])


def coal_convex(vertices: np.ndarray, faces: np.ndarray | None = None) -> coal.Convex:
    """A coal convex shape from ``vertices (V, 3)`` (hull faces computed when not given)."""
    vertices = np.asarray(vertices, dtype=float)
    if faces is None:
        hull = trimesh.convex.convex_hull(vertices)
        vertices, faces = np.asarray(hull.vertices), np.asarray(hull.faces)
    pts = coal.StdVec_Vec3s()
    for p in vertices:
        pts.append(p)
    tris = coal.StdVec_Triangle()
    for f in np.asarray(faces, dtype=int):
        tris.append(coal.Triangle(int(f[0]), int(f[1]), int(f[2])))
    return coal.Convex(pts, tris)


@dataclass
class _CoalPart:
    part: HandPart
    shape: coal.Convex
    center: np.ndarray  # (3,) bounding-sphere centre, TCP frame at zero opening
    radius: float


class PandaHandCollisionModel:
    """The hand as coal convex shapes, placed by a TCP pose and a finger opening.

    ``approach_sweep`` as in :func:`hand_parts`. Obstacles are coal shapes in the world
    frame (identity placement) with bounding spheres for a cheap pre-filter.
    """

    def __init__(self, approach_sweep: float = 0.0, include_wrist: bool = True, security_margin: float = 0.002):
        self.parts = [
            _CoalPart(p, coal_convex(p.vertices, p.faces), *_bounding_sphere(p.vertices))
            for p in hand_parts(float(approach_sweep), bool(include_wrist))
        ]
        self.security_margin = float(security_margin)
        self._request = coal.CollisionRequest()
        self._request.security_margin = self.security_margin
        self._identity = coal.Transform3s()

    def part_vertices_world(self, poses: np.ndarray, openings: np.ndarray) -> np.ndarray:
        """``(M, V_total, 3)`` world vertices of all parts for ``poses (M, 4, 4)``, ``openings (M,)``."""
        local = [p.part.vertices[None] + p.part.offset(openings)[:, None] for p in self.parts]
        pts = np.concatenate(local, axis=1)  # (M, V, 3) TCP frame
        return pts @ np.swapaxes(poses[:, :3, :3], 1, 2) + poses[:, None, :3, 3]

    def collides(
        self,
        pose: np.ndarray,
        opening: float,
        obstacles: list[coal.CollisionGeometry],
        obstacle_spheres: np.ndarray,
    ) -> bool:
        """Whether the hand at TCP ``pose (4, 4)`` with ``opening`` (m) touches any obstacle
        (within ``security_margin``). ``obstacle_spheres (K, 4)``: world centre + radius."""
        rot, pos = pose[:3, :3], pose[:3, 3]
        result = coal.CollisionResult()
        for p in self.parts:
            shift = p.part.offset(np.array(opening))
            center = rot @ (p.center + shift) + pos
            dist = np.linalg.norm(obstacle_spheres[:, :3] - center, axis=1)
            near = np.flatnonzero(dist <= obstacle_spheres[:, 3] + p.radius + self.security_margin)
            if near.size == 0:
                continue
            tf = coal.Transform3s(rot, rot @ shift + pos)
            for k in near:
                result.clear()
                if coal.collide(p.shape, tf, obstacles[k], self._identity, self._request, result):
                    return True
        return False


def _bounding_sphere(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = vertices.min(0), vertices.max(0)
    center = (lo + hi) / 2
    return center, float(np.linalg.norm(vertices - center, axis=1).max())
