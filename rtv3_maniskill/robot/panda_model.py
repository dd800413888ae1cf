"""Pinocchio model of ManiSkill's Panda: kinematics, IK and the collision world.

Everything is in the **world frame** of the ManiSkill scene: the robot base
(``panda_link0``) stands at ``ROBOT_BASE_POSITION`` with identity rotation, the table
top is at z = 0.

End-effector frame: ManiSkill's TCP link ``panda_hand_tcp`` (10.34 cm in front of
``panda_hand``, between the finger pads). Its **z axis is the approach axis** (from the
hand towards the fingertips) and its **y axis the finger closing axis** (the finger
joints slide along +-y of ``panda_hand``, which has the same rotation as the TCP); this
matches ``mani_skill.agents.robots.panda.Panda.build_grasp_pose``, whose rotation
columns are ``[closing x approaching, closing, approaching]``.

The fingers are locked open (0.04 m each) in this model: planning happens with the
gripper open.

Collision geometry: the URDF's 17 collision geometries (9 link meshes + 8 finger
boxes). Link meshes are replaced by their convex hulls, which is what SAPIEN/PhysX
simulates. Self-collision pairs follow ManiSkill's ``panda_v2.srdf``.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin
import trimesh

from rtv3_maniskill.robot.scene_geometry import (
    ROBOT_BASE_POSITION,
    TABLE_TOP_CENTER,
    TABLE_TOP_HALF_SIZE,
    CollisionShape,
    SceneGeometry,
)

ARM_JOINT_NAMES = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINT_NAMES = ("panda_finger_joint1", "panda_finger_joint2")
TCP_FRAME_NAME = "panda_hand_tcp"
FINGER_OPEN = 0.04
"""Finger joint position (m, each finger) used during planning."""

REST_QPOS = np.array([0.0, np.pi / 8, 0.0, -np.pi * 5 / 8, 0.0, np.pi * 3 / 4, np.pi / 4])
"""ManiSkill's Panda ``rest`` keyframe (arm joints only)."""

PANDA_VELOCITY_LIMITS = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
"""Joint velocity limits (rad/s) from the URDF."""
PANDA_ACCELERATION_LIMITS = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])
"""Joint acceleration limits (rad/s^2) from Franka's datasheet (the URDF has none)."""

DOF = 7


def panda_asset_dir() -> Path:
    """Folder of ManiSkill's Panda assets inside the installed ``mani_skill`` wheel."""
    spec = importlib.util.find_spec("mani_skill")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("mani_skill is not installed; the Panda URDF ships with it")
    path = Path(list(spec.submodule_search_locations)[0]) / "assets" / "robots" / "panda"
    if not (path / "panda_v2.urdf").is_file():
        raise FileNotFoundError(f"panda_v2.urdf not found in {path}")
    return path


def as_joint_vector(q, name: str = "q") -> np.ndarray:
    """Validate a ``(7,)`` arm configuration and return it as float64."""
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (DOF,):
        raise ValueError(f"{name} must have shape (7,) (Panda arm joints), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf: {arr}")
    return arr


def as_pose_matrix(pose, name: str = "pose") -> np.ndarray:
    """Validate a ``(4, 4)`` rigid transform and return it as float64."""
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) homogeneous matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    rot = arr[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(rot) - 1.0) > 1e-4:
        raise ValueError(f"{name} has a rotation block that is not a proper rotation matrix")
    if np.abs(arr[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        raise ValueError(f"{name} must have last row [0, 0, 0, 1], got {arr[3]}")
    return arr


class PandaKinematics:
    """Panda arm (7 joints, fingers locked open) in the world frame, with TCP IK.

    ``q`` is always ``(7,)`` arm joint positions in radians (ManiSkill's qpos[:7]).
    """

    def __init__(self, base_position: np.ndarray = ROBOT_BASE_POSITION) -> None:
        asset_dir = panda_asset_dir()
        self.urdf_path = asset_dir / "panda_v2.urdf"
        self.srdf_path = asset_dir / "panda_v2.srdf"
        full = pin.buildModelFromUrdf(str(self.urdf_path))
        geom = pin.buildGeomFromUrdf(full, str(self.urdf_path), pin.GeometryType.COLLISION,
                                     package_dirs=[str(asset_dir)])
        # Placing the robot: append it to an empty world model at the base pose.
        base = pin.SE3(np.eye(3), np.asarray(base_position, dtype=np.float64))
        full, geom = pin.appendModel(pin.Model(), full, pin.GeometryModel(), geom, 0, base)
        q_ref = pin.neutral(full)
        lock = []
        for name in FINGER_JOINT_NAMES:
            jid = full.getJointId(name)
            q_ref[full.joints[jid].idx_q] = FINGER_OPEN
            lock.append(jid)
        self.model, self.robot_geometry = pin.buildReducedModel(full, geom, lock, q_ref)
        names = [self.model.names[j] for j in range(1, self.model.njoints)]
        if tuple(names) != ARM_JOINT_NAMES:
            raise RuntimeError(f"unexpected joint order in the reduced Panda model: {names}")
        for g in self.robot_geometry.geometryObjects:
            if isinstance(g.geometry, coal.BVHModelBase):
                g.geometry.buildConvexRepresentation(False)
                g.geometry = g.geometry.convex
        self.data = self.model.createData()
        self.tcp_frame_id = self.model.getFrameId(TCP_FRAME_NAME)
        self.lower = self.model.lowerPositionLimit.copy()
        self.upper = self.model.upperPositionLimit.copy()
        self.base_pose = base.homogeneous

    # ------------------------------------------------------------------ kinematics

    def forward_kinematics(self, q) -> np.ndarray:
        """``(4, 4)`` TCP pose in the world frame for arm joints ``q (7,)``."""
        q = as_joint_vector(q)
        pin.framesForwardKinematics(self.model, self.data, q)
        return self.data.oMf[self.tcp_frame_id].homogeneous.copy()

    def frame_pose(self, q, frame_name: str) -> np.ndarray:
        """``(4, 4)`` world pose of any URDF link/frame (e.g. ``panda_hand``)."""
        q = as_joint_vector(q)
        pin.framesForwardKinematics(self.model, self.data, q)
        return self.data.oMf[self.model.getFrameId(frame_name)].homogeneous.copy()

    def tcp_jacobian(self, q) -> np.ndarray:
        """``(6, 7)`` TCP Jacobian in the TCP (body) frame, rows ``[v, w]``."""
        q = as_joint_vector(q)
        return pin.computeFrameJacobian(self.model, self.data, q, self.tcp_frame_id, pin.LOCAL).copy()

    def tcp_linear_jacobian_world(self, q) -> np.ndarray:
        """``(3, 7)`` world-frame linear velocity Jacobian of the TCP origin."""
        q = as_joint_vector(q)
        jac = pin.computeFrameJacobian(self.model, self.data, q, self.tcp_frame_id, pin.LOCAL_WORLD_ALIGNED)
        return jac[:3].copy()

    def within_limits(self, q, tol: float = 0.0) -> bool:
        """Whether ``q (7,)`` lies within the joint limits (plus ``tol`` rad)."""
        q = as_joint_vector(q)
        return bool(np.all(q >= self.lower - tol) and np.all(q <= self.upper + tol))

    def random_configuration(self, rng: np.random.Generator, margin: float = 0.0) -> np.ndarray:
        """Uniform ``(7,)`` configuration within the limits shrunk by ``margin`` rad."""
        return rng.uniform(self.lower + margin, self.upper - margin)

    # ------------------------------------------------------------------ IK

    def ik_from_seed(
        self,
        target: np.ndarray,
        q_seed: np.ndarray,
        *,
        max_iters: int = 200,
        pos_tol: float = 1e-4,
        rot_tol: float = 1e-3,
        damping: float = 1e-4,
        max_step: float = 0.3,
        limit_margin: float = 1e-3,
    ) -> tuple[np.ndarray, bool]:
        """Damped least-squares IK of the TCP from one seed.

        ``target`` ``(4, 4)`` world pose, ``q_seed`` ``(7,)``. Iterates
        ``dq = -J^T (J J^T + lambda I)^-1 e`` on the body-frame error
        ``e = log6(T_tcp^-1 T_target)`` (with the log's Jacobian, so steps are exact to
        first order), clamping to the joint limits. Returns ``(q, converged)``;
        converged means position error < ``pos_tol`` m and rotation error <
        ``rot_tol`` rad.
        """
        target_se3 = pin.SE3(target[:3, :3], target[:3, 3])
        lower = self.lower + limit_margin
        upper = self.upper - limit_margin
        q = np.clip(np.asarray(q_seed, dtype=np.float64), lower, upper)
        model, data, fid = self.model, self.data, self.tcp_frame_id
        eye6 = np.eye(6)
        for _ in range(max_iters):
            pin.forwardKinematics(model, data, q)
            current = pin.updateFramePlacement(model, data, fid)
            i_m_d = current.actInv(target_se3)
            err = pin.log6(i_m_d).vector
            if np.linalg.norm(err[:3]) < pos_tol and np.linalg.norm(err[3:]) < rot_tol:
                return q, True
            pin.computeJointJacobians(model, data, q)
            jac = pin.getFrameJacobian(model, data, fid, pin.LOCAL)
            jac = -pin.Jlog6(i_m_d.inverse()) @ jac
            dq = -jac.T @ np.linalg.solve(jac @ jac.T + damping * eye6, err)
            norm = np.abs(dq).max()
            if norm > max_step:
                dq *= max_step / norm
            q = np.clip(q + dq, lower, upper)
        return q, False


# ---------------------------------------------------------------------- collision world


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

    def min_distance(self, q, ignore_objects: Iterable[int] = ()) -> float:
        """Smallest distance (m, margins not subtracted) between the robot and any obstacle.

        Negative or 0 when in contact. Self-collision pairs are not included.
        """
        q = as_joint_vector(q)
        self.set_ignored(ignore_objects)
        pin.updateGeometryPlacements(self.model, self.data, self.geometry, self.geometry_data, q)
        best = np.inf
        for obj_idx, pair_ids in self.pairs_by_object.items():
            if obj_idx in self._ignored:
                continue
            for p in pair_ids:
                res = pin.computeDistance(self.geometry, self.geometry_data, p)
                best = min(best, res.min_distance)
        return float(best)


    # ------------------------------------------------------------------ distance queries (reactive control)

    def robot_geometry_names(self) -> list[str]:
        """Names of the robot's collision geometries, indexed like ``robot_geometry_ids``."""
        return [self.geometry.geometryObjects[i].name for i in self.robot_geometry_ids]

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
