"""Plain description of a clutter scene's collision geometry.

One description serves the simulator (ManiSkill actors), the grasp sampler's hand
collision check and the motion planner's collision model, so they agree on what is
where. Frames: object shapes are given in the object frame; object poses in the world
frame of the ManiSkill scene (z up, table surface at z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import trimesh

# The authors' placement (docs/PAPER_DETAILS.md, "Authors' benchmark protocol"): the Panda base
# stands 0.45 m behind the workspace centre and 0.15 m below the workspace floor (the table top),
# so that the ready pose holds the TCP 0.34 m above the table at the workspace's near edge.
# ManiSkill's TableSceneBuilder table (a kinematic box, top at z = 0, 1.209 m deep, 2.418 m wide)
# is moved so that its near edge clears the robot's shoulder by 10 cm; only its top slab matters
# for collisions.
ROBOT_BASE_POSITION = np.array([-0.50, 0.0, -0.15])
TABLE_NEAR_EDGE_X = -0.40
TABLE_TOP_HALF_SIZE = np.array([0.6045, 1.209, 0.025])
TABLE_TOP_CENTER = np.array([TABLE_NEAR_EDGE_X + TABLE_TOP_HALF_SIZE[0], 0.0, -0.025])
READY_QPOS = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])
"""The Panda ready pose (arm joints, rad): every shared-control trial starts here, TCP pointing down."""
WORKSPACE_CENTER = np.array([-0.05, 0.0, 0.15])
"""Centre of the 30 x 30 x 30 cm workspace cube (world frame, resting on the table)."""
WORKSPACE_HALF_SIZE = 0.15

ShapeKind = Literal["box", "sphere", "cylinder", "capsule", "convex"]

# Rotation taking SAPIEN's cylinder/capsule axis (x) to the object's z axis.
_X_TO_Z = trimesh.transformations.rotation_matrix(-np.pi / 2, [0, 1, 0])


def translation(x: float, y: float, z: float, base: np.ndarray | None = None) -> np.ndarray:
    """``(4, 4)`` ``base`` (default identity) with its translation set to ``(x, y, z)``."""
    pose = np.eye(4) if base is None else base.copy()
    pose[:3, 3] = [x, y, z]
    return pose


@dataclass
class CollisionShape:
    """One convex collision primitive of an object.

    ``params`` by kind (metres): box ``(hx, hy, hz)`` half sizes; sphere ``(r,)``;
    cylinder and capsule ``(r, half_length)`` with the axis along the local **x** axis
    (SAPIEN's convention); convex: ``()`` and ``vertices (V, 3)``.
    ``local_pose`` ``(4, 4)`` places the shape in the object frame.
    """

    kind: ShapeKind
    params: tuple[float, ...] = ()
    local_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    vertices: np.ndarray | None = None

    def to_trimesh(self) -> trimesh.Trimesh:
        """A triangle mesh of this shape in the object frame."""
        if self.kind == "box":
            mesh = trimesh.creation.box(extents=2 * np.asarray(self.params))
        elif self.kind == "sphere":
            mesh = trimesh.creation.icosphere(subdivisions=2, radius=self.params[0])
        elif self.kind in ("cylinder", "capsule"):
            radius, half_length = self.params
            if self.kind == "cylinder":
                mesh = trimesh.creation.cylinder(radius=radius, height=2 * half_length, sections=24)
            else:
                mesh = trimesh.creation.capsule(radius=radius, height=2 * half_length, count=[24, 12])
            # trimesh builds along z; SAPIEN's axis is x.
            mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        elif self.kind == "convex":
            mesh = trimesh.convex.convex_hull(np.asarray(self.vertices))
        else:
            raise ValueError(f"unknown collision shape kind {self.kind!r}")
        mesh.apply_transform(self.local_pose)
        return mesh


def upright_cylinder(radius: float, half_length: float, z0: float, kind: str = "cylinder") -> CollisionShape:
    """A cylinder (or capsule) standing on ``z = z0`` (its lowest point), axis along the object's z."""
    bottom = half_length + (radius if kind == "capsule" else 0.0)
    return CollisionShape(kind, (radius, half_length), translation(0, 0, z0 + bottom, _X_TO_Z))


@dataclass
class ObjectGeometry:
    """A rigid object: its convex parts, a visual mesh and a colour, in its own frame."""

    name: str
    shapes: list[CollisionShape]
    visual_mesh: trimesh.Trimesh
    color: tuple[float, float, float, float] = (0.6, 0.6, 0.6, 1.0)
    density: float = 500.0
    mesh_file: str | None = None
    """Source mesh file for objects loaded from a folder (None for procedural ones)."""

    def collision_mesh(self) -> trimesh.Trimesh:
        """All convex parts merged into one mesh (object frame)."""
        return trimesh.util.concatenate([s.to_trimesh() for s in self.shapes])


@dataclass
class SceneGeometry:
    """Objects placed in the world plus the table top as an obstacle.

    ``object_poses`` ``(n, 4, 4)`` world-from-object transforms. The table occupies
    ``z <= 0`` over ``table_half_size`` around ``table_center``.
    """

    objects: list[ObjectGeometry]
    object_poses: np.ndarray
    table_center: np.ndarray = field(default_factory=lambda: TABLE_TOP_CENTER.copy())
    table_half_size: np.ndarray = field(default_factory=lambda: TABLE_TOP_HALF_SIZE.copy())

    def world_meshes(self) -> list[trimesh.Trimesh]:
        """One collision mesh per object, in the world frame."""
        meshes = []
        for obj, pose in zip(self.objects, self.object_poses):
            mesh = obj.collision_mesh()
            mesh.apply_transform(pose)
            meshes.append(mesh)
        return meshes
