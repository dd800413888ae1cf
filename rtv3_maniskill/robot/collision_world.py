"""Collision model of ManiSkill's Panda in a clutter scene (Pinocchio + coal), world frame.

Robot geometry: the URDF's collision geometries as built by
:class:`~rtv3_maniskill.robot.panda_model.PandaKinematics` (link meshes replaced by their
convex hulls, which is what SAPIEN/PhysX simulates, fingers locked open). Obstacles: the table
top slab and every convex part of every object of a :class:`SceneGeometry`. Self-collision
pairs follow ManiSkill's ``panda_v2.srdf``.

Queries: collision checks with per-kind security margins (the motion planner), colliding pair
names (diagnostics), and signed distances with witness points (the NEO reactive controller).
Joint vectors are ``(7,)`` arm joints in radians; ``ignore_objects`` holds object indices,
``TABLE_OBJECT_INDEX`` (-1) for the table.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin
import trimesh

from rtv3_maniskill.robot.panda_model import PandaKinematics, as_joint_vector
from rtv3_maniskill.robot.scene_geometry import (
    TABLE_TOP_CENTER,
    TABLE_TOP_HALF_SIZE,
    CollisionShape,
    SceneGeometry,
)


def _shape_to_coal(shape: CollisionShape) -> tuple[coal.CollisionGeometry, np.ndarray]:
    """A scene ``CollisionShape`` as a coal geometry and the ``(4, 4)`` pose fix-up.

    coal's ``Box`` takes full extents; ``Cylinder``/``Capsule`` take the full length
    and lie along z, whereas the scene (SAPIEN) convention puts their axis along x:
    the returned ``(4, 4)`` rotates coal's z onto the shape's x.
    """
    fix = np.eye(4)
    if shape.kind == "box":
        hx, hy, hz = shape.params
        return coal.Box(2 * hx, 2 * hy, 2 * hz), fix
    if shape.kind == "sphere":
        return coal.Sphere(float(shape.params[0])), fix
    if shape.kind in ("cylinder", "capsule"):
        radius, half_length = shape.params
        # Rotation about y by +90 deg maps z -> x.
        fix[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
        cls = coal.Cylinder if shape.kind == "cylinder" else coal.Capsule
        return cls(float(radius), float(2 * half_length)), fix
    if shape.kind == "convex":
        if shape.vertices is None or np.asarray(shape.vertices).ndim != 2 or np.asarray(shape.vertices).shape[1] != 3:
            raise ValueError("convex CollisionShape needs vertices of shape (V, 3)")
        mesh = trimesh.convex.convex_hull(np.asarray(shape.vertices, dtype=np.float64))  # shape frame
        bvh = coal.BVHModelOBBRSS()
        bvh.beginModel(len(mesh.faces), len(mesh.vertices))
        bvh.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
        bvh.addTriangles(np.asarray(mesh.faces, dtype=np.int64))
        bvh.endModel()
        bvh.buildConvexRepresentation(False)
        return bvh.convex, fix
    raise ValueError(f"unknown collision shape kind {shape.kind!r}")


@dataclass(frozen=True)
class CollisionMargins:
    """Security margins (m) added to collision checks, per pair kind.

    ``objects``: robot vs scene objects; ``table``: robot vs table top; ``self``: robot
    vs itself. A margin makes plans robust to the PD controller's tracking error.
    """

    objects: float = 0.01
    table: float = 0.005
    self: float = 0.0


TABLE_OBJECT_INDEX = -1
"""Object index used for the table top in ``ignore_objects`` sets."""


class PandaCollisionWorld:
    """Robot + scene collision model for one ``SceneGeometry`` (world frame).

    Pairs checked: robot self-collisions not disabled by ManiSkill's SRDF, robot links
    vs every convex part of every object, and robot links vs the table top slab
    (except ``panda_link0``, which stands on it).
    """

    def __init__(
        self,
        kinematics: PandaKinematics,
        scene: SceneGeometry | None = None,
        margins: CollisionMargins = CollisionMargins(),
    ) -> None:
        self.kin = kinematics
        self.margins = margins
        self.model = kinematics.model
        self.data = self.model.createData()
        self._robot_self_pairs = self._srdf_self_pairs()
        self.set_scene(scene)

    def _srdf_self_pairs(self) -> list[tuple[int, int]]:
        robot = self.kin.robot_geometry.copy()
        robot.addAllCollisionPairs()
        pin.removeCollisionPairs(self.model, robot, str(self.kin.srdf_path))
        pairs = []
        for cp in robot.collisionPairs:
            a, b = cp.first, cp.second
            # Geometries on the same rigid body (e.g. hand and locked fingers) never move apart.
            if robot.geometryObjects[a].parentJoint == robot.geometryObjects[b].parentJoint:
                continue
            pairs.append((a, b))
        return pairs

    def set_scene(self, scene: SceneGeometry | None) -> None:
        """Replace the obstacles by those of ``scene`` (None: table only)."""
        geom = self.kin.robot_geometry.copy()
        n_robot = geom.ngeoms
        self.robot_geometry_ids = list(range(n_robot))
        self.object_geometry_ids: dict[int, list[int]] = {}
        table_half = np.asarray(scene.table_half_size if scene is not None else TABLE_TOP_HALF_SIZE, dtype=np.float64)
        table_center = np.asarray(scene.table_center if scene is not None else TABLE_TOP_CENTER, dtype=np.float64)
        table = coal.Box(*(2 * table_half))
        tid = geom.addGeometryObject(pin.GeometryObject("table_top", 0, 0, pin.SE3(np.eye(3), table_center), table))
        self.object_geometry_ids[TABLE_OBJECT_INDEX] = [tid]
        if scene is not None:
            poses = np.asarray(scene.object_poses, dtype=np.float64)
            if poses.shape != (len(scene.objects), 4, 4):
                raise ValueError(f"scene.object_poses must be ({len(scene.objects)}, 4, 4), got {poses.shape}")
            for idx, (obj, pose) in enumerate(zip(scene.objects, poses)):
                ids = []
                for k, shape in enumerate(obj.shapes):
                    coal_geom, fix = _shape_to_coal(shape)
                    placement = pose @ np.asarray(shape.local_pose, dtype=np.float64) @ fix
                    go = pin.GeometryObject(f"obj{idx}_{obj.name}_{k}", 0, 0,
                                            pin.SE3(placement[:3, :3], placement[:3, 3]), coal_geom)
                    ids.append(geom.addGeometryObject(go))
                self.object_geometry_ids[idx] = ids
        link0 = [i for i in self.robot_geometry_ids if geom.geometryObjects[i].name.startswith("panda_link0")]
        self._pair_kinds: list[str] = []
        for a, b in self._robot_self_pairs:
            geom.addCollisionPair(pin.CollisionPair(a, b))
            self._pair_kinds.append("self")
        self.pairs_by_object: dict[int, list[int]] = {}
        for obj_idx, ids in self.object_geometry_ids.items():
            self.pairs_by_object[obj_idx] = []
            for oid in ids:
                for rid in self.robot_geometry_ids:
                    if obj_idx == TABLE_OBJECT_INDEX and rid in link0:
                        continue
                    geom.addCollisionPair(pin.CollisionPair(rid, oid))
                    self.pairs_by_object[obj_idx].append(len(geom.collisionPairs) - 1)
                    self._pair_kinds.append("table" if obj_idx == TABLE_OBJECT_INDEX else "objects")
        self.geometry = geom
        self.geometry_data = pin.GeometryData(geom)
        self.set_margins(self.margins)
        # AABB-tree broad phase (pinocchio inflates the boxes by each pair's margin and
        # honours deactivated pairs); 5x faster than checking every pair in clutter.
        self._broadphase = pin.BroadPhaseManager_DynamicAABBTreeCollisionManager(self.model, self.geometry,
                                                                                 self.geometry_data)
        self.num_objects = len(scene.objects) if scene is not None else 0
        self._ignored: frozenset[int] = frozenset()

    def set_margins(self, margins: CollisionMargins) -> None:
        """Change the security margins of all collision pairs."""
        self.margins = margins
        for k, kind in enumerate(self._pair_kinds):
            self.geometry_data.collisionRequests[k].security_margin = float(getattr(margins, kind))

    def set_ignored(self, ignore_objects: Iterable[int]) -> None:
        """Deactivate the robot pairs of the objects in ``ignore_objects`` (re-activate the others)."""
        ignore = frozenset(int(i) for i in ignore_objects)
        if ignore == self._ignored:
            return
        unknown = ignore - set(self.pairs_by_object)
        if unknown:
            raise ValueError(f"ignore_objects has unknown object indices {sorted(unknown)} "
                             f"(scene has {self.num_objects}, table = {TABLE_OBJECT_INDEX})")
        for obj_idx, pair_ids in self.pairs_by_object.items():
            for p in pair_ids:
                if obj_idx in ignore:
                    self.geometry_data.deactivateCollisionPair(p)
                else:
                    self.geometry_data.activateCollisionPair(p)
        self._ignored = ignore

    def is_collision_free(self, q, ignore_objects: Iterable[int] = ()) -> bool:
        """Whether ``q (7,)`` is within limits and free of collisions (margins included).

        ``ignore_objects``: object indices (``TABLE_OBJECT_INDEX`` for the table) whose
        contacts with the robot are not checked.
        """
        q = as_joint_vector(q)
        if not self.kin.within_limits(q, tol=1e-6):
            return False
        self.set_ignored(ignore_objects)
        return not pin.computeCollisions(self.model, self.data, self._broadphase, q, True)

    def check_fast(self, q: np.ndarray) -> bool:
        """``is_collision_free`` without input validation or limit check (OMPL's hot loop).

        Uses the ignore set of the last validated call.
        """
        return not pin.computeCollisions(self.model, self.data, self._broadphase, q, True)

    def last_tcp_position(self) -> np.ndarray:
        """``(3,)`` world TCP position (m) of the configuration last checked (a check runs its kinematics)."""
        return pin.updateFramePlacement(self.model, self.data, self.kin.tcp_frame_id).translation

    def colliding_pairs(self, q, ignore_objects: Iterable[int] = ()) -> list[tuple[str, str]]:
        """Names of all geometry pairs in collision at ``q (7,)`` (diagnostics)."""
        q = as_joint_vector(q)
        self.set_ignored(ignore_objects)
        pin.computeCollisions(self.model, self.data, self.geometry, self.geometry_data, q, False)
        out = []
        for k, cp in enumerate(self.geometry.collisionPairs):
            if self.geometry_data.activeCollisionPairs[k] and self.geometry_data.collisionResults[k].isCollision():
                out.append((self.geometry.geometryObjects[cp.first].name,
                            self.geometry.geometryObjects[cp.second].name))
        return out

    # ------------------------------------------------------------------ distance queries (reactive control)

    def obstacle_pairs(self) -> list[tuple[int, int, int]]:
        """``(pair index, robot geometry id, object index)`` of every robot-obstacle pair.

        Object index ``TABLE_OBJECT_INDEX`` (-1) is the table top.
        """
        out = []
        for obj_idx, pair_ids in self.pairs_by_object.items():
            for p in pair_ids:
                out.append((p, self.geometry.collisionPairs[p].first, obj_idx))
        return out

    def nearest_points(self, q, pair_ids: np.ndarray, max_distance: float) -> NearestPoints:
        """Signed distances and nearest points (world frame) of robot-obstacle pairs at ``q (7,)``.

        ``pair_ids (P,)``: indices into the collision pairs (see ``obstacle_pairs``). Pairs whose
        bounding spheres are farther apart than ``max_distance`` (m) are culled before the exact
        (coal GJK/EPA) query; of the others, those with distance ``<= max_distance`` are returned.
        Also runs the forward kinematics of ``q`` into ``self.data`` (joint placements).
        """
        q = as_joint_vector(q)
        pair_ids = np.asarray(pair_ids, dtype=np.int64).reshape(-1)
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateGeometryPlacements(self.model, self.data, self.geometry, self.geometry_data)
        cache = getattr(self, "_distance_cache", None)
        if cache is None or cache[0] is not self.geometry:  # built once per scene (set_scene makes a new model)
            objs = self.geometry.geometryObjects
            centers = np.array([np.asarray(g.geometry.aabb_center, dtype=np.float64) for g in objs])
            radii = np.array([float(g.geometry.aabb_radius) for g in objs])
            parents = np.array([g.parentJoint for g in objs], dtype=np.int64)
            firsts = np.array([cp.first for cp in self.geometry.collisionPairs], dtype=np.int64)
            seconds = np.array([cp.second for cp in self.geometry.collisionPairs], dtype=np.int64)
            # Obstacles are fixed in the world (joint 0): their bounding-sphere centres once.
            world = np.array([self.geometry_data.oMg[i].act(centers[i]) for i in range(len(objs))])
            cache = (self.geometry, centers, radii, parents, firsts, seconds, world)
            self._distance_cache = cache
        _, centers, radii, parents, firsts, seconds, world_centers = cache
        world_centers = world_centers.copy()
        for i in self.robot_geometry_ids:
            world_centers[i] = self.geometry_data.oMg[i].act(centers[i])
        a, b = firsts[pair_ids], seconds[pair_ids]
        gap = np.linalg.norm(world_centers[a] - world_centers[b], axis=1) - radii[a] - radii[b]
        keep = pair_ids[gap <= max_distance]
        rows = []
        for p in keep:
            res = pin.computeDistance(self.geometry, self.geometry_data, int(p))
            if res.min_distance <= max_distance:
                rows.append((int(p), res.min_distance, res.getNearestPoint1(), res.getNearestPoint2(), res.normal))
        if not rows:
            empty, none = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
            return NearestPoints(none, np.zeros(0), empty, empty.copy(), empty.copy(), none.copy())
        pairs = np.array([r[0] for r in rows], dtype=np.int64)
        first = firsts[pairs]
        return NearestPoints(
            pair_ids=pairs,
            distances=np.array([r[1] for r in rows]),
            robot_points=np.array([r[2] for r in rows]),
            obstacle_points=np.array([r[3] for r in rows]),
            normals=np.array([r[4] for r in rows]),
            robot_joints=parents[first],
        )


@dataclass(frozen=True)
class NearestPoints:
    """Result of ``PandaCollisionWorld.nearest_points`` for ``K`` robot-obstacle pairs (world frame).

    ``distances (K,)`` signed (m, negative when penetrating); ``robot_points``/``obstacle_points``
    ``(K, 3)`` the witness points; ``normals (K, 3)`` unit vectors from the robot towards the
    obstacle (the distance shrinks when the robot point moves along them); ``robot_joints (K,)``
    the Pinocchio joint that carries each robot geometry.
    """

    pair_ids: np.ndarray
    distances: np.ndarray
    robot_points: np.ndarray
    obstacle_points: np.ndarray
    normals: np.ndarray
    robot_joints: np.ndarray
