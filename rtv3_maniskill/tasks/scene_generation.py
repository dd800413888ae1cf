"""Clutter layouts following the VGN / GIGA protocol (docs/PAPER_DETAILS.md, "Scene generation").

A layout is computed in a private, physics-only SAPIEN scene (no rendering, CPU PhysX):
objects are dropped (``pile``) or placed upright (``packed``) in the workspace and
simulated until they rest. The resulting :class:`SceneGeometry` is then loaded into the
ManiSkill task, where the objects start at rest. Same seed -> same layout.

Frames: world = ManiSkill scene frame; the workspace is the 30 cm cube around
``WORKSPACE_CENTER`` standing on the table (z = 0).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import sapien
import torch

from rtv3_maniskill.robot.scene_geometry import (
    WORKSPACE_CENTER,
    WORKSPACE_HALF_SIZE,
    CollisionShape,
    ObjectGeometry,
    SceneGeometry,
)
from rtv3_maniskill.se3 import matrix_to_quat, quat_to_matrix
from rtv3_maniskill.tasks.convex_cache import convex_part_file
from rtv3_maniskill.tasks.object_library import ObjectSet

SceneType = Literal["pile", "packed", "packed_ycb"]
SCENE_TYPES = ("pile", "packed", "packed_ycb")
"""Layouts: VGN's pile and packed scenes, and the RT-V3 authors' YCB packed validation scenes."""
PACKED_YCB_OBJECTS = 4
"""Distinct objects a ``packed_ycb`` scene asks for; at least ``PACKED_YCB_MIN_OBJECTS`` are kept."""
PACKED_YCB_MIN_OBJECTS = 3
PACKED_YCB_SCALE = 0.8
PACKED_YCB_HALF_RANGE = 0.10
"""Object positions: x, y uniform in [0.05, 0.25] m of the 30 cm workspace, i.e. centre +- 0.10 m."""
PACKED_YCB_ATTEMPTS = 12
_SIM_DT = 1.0 / 100.0  # ManiSkill's sim_freq for this task, so layouts rest in both


def matrix_to_sapien_pose(matrix: np.ndarray) -> sapien.Pose:
    pose = sapien.Pose()
    pose.set_p(matrix[:3, 3])
    pose.set_q(_rot_to_quat(matrix[:3, :3]))
    return pose


def sapien_pose_to_matrix(pose: sapien.Pose) -> np.ndarray:
    return pose.to_transformation_matrix()


def _rot_to_quat(rot: np.ndarray) -> np.ndarray:
    return matrix_to_quat(torch.as_tensor(rot, dtype=torch.float64)).numpy()


def add_collision_shapes(builder, shapes: list[CollisionShape], material=None, density: float = 500.0) -> None:
    """Add an object's convex parts to a SAPIEN / ManiSkill actor builder."""
    for shape in shapes:
        pose = matrix_to_sapien_pose(shape.local_pose)
        if shape.kind == "box":
            builder.add_box_collision(pose, half_size=shape.params, material=material, density=density)
        elif shape.kind == "sphere":
            builder.add_sphere_collision(pose, radius=shape.params[0], material=material, density=density)
        elif shape.kind == "cylinder":
            builder.add_cylinder_collision(pose, radius=shape.params[0], half_length=shape.params[1], material=material,
                                           density=density)
        elif shape.kind == "capsule":
            builder.add_capsule_collision(pose, radius=shape.params[0], half_length=shape.params[1], material=material,
                                          density=density)
        elif shape.kind == "convex":
            builder.add_convex_collision_from_file(convex_part_file(shape.vertices), pose, material=material,
                                                   density=density)
        else:
            raise ValueError(f"unknown collision shape kind {shape.kind!r}")


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (normalised Gaussian quaternion)."""
    return quat_to_matrix(torch.as_tensor(rng.normal(size=4))).numpy()


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _SettleScene:
    """A physics-only SAPIEN scene with the table top, used to let objects come to rest."""

    def __init__(self):
        self.scene = sapien.Scene([sapien.physx.PhysxCpuSystem()])
        self.scene.set_timestep(_SIM_DT)
        self.material = sapien.physx.PhysxMaterial(0.6, 0.5, 0.0)
        ground = self.scene.create_actor_builder()
        ground.add_box_collision(sapien.Pose([0, 0, -0.05]), half_size=[1.0, 1.0, 0.05], material=self.material)
        ground.build_static("table")
        self.actors: list[sapien.Entity] = []
        self.walls: list[sapien.Entity] = []

    def add(self, obj: ObjectGeometry, pose: np.ndarray) -> sapien.Entity:
        builder = self.scene.create_actor_builder()
        add_collision_shapes(builder, obj.shapes, self.material, obj.density)
        actor = builder.build(obj.name)
        actor.set_pose(matrix_to_sapien_pose(pose))
        # No sleeping: a body put to sleep in a marginal pose would pass the rest checks here and
        # then slide once the task wakes it up.
        actor.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent).set_sleep_threshold(0.0)
        self.actors.append(actor)
        return actor

    def add_walls(self, center: np.ndarray, half_inner: float, height: float = 0.3, thickness: float = 0.01) -> None:
        builder = self.scene.create_actor_builder()
        for axis in (0, 1):
            for sign in (-1, 1):
                offset = np.zeros(3)
                offset[axis] = sign * (half_inner + thickness)
                half = ([thickness, half_inner + 2 * thickness, height / 2] if axis == 0
                        else [half_inner + 2 * thickness, thickness, height / 2])
                builder.add_box_collision(sapien.Pose([center[0] + offset[0], center[1] + offset[1], height / 2]),
                                          half_size=half, material=self.material)
        self.walls.append(builder.build_static("walls"))

    def remove_walls(self) -> None:
        for wall in self.walls:
            self.scene.remove_entity(wall)
        self.walls = []

    def remove(self, actor: sapien.Entity) -> None:
        self.scene.remove_entity(actor)
        self.actors.remove(actor)

    def settle(self, max_time: float = 2.0, check_every: int = 10) -> None:
        """Step until every object is at rest (speeds < 1 cm/s, 0.1 rad/s) or ``max_time``."""
        for step in range(int(max_time / _SIM_DT)):
            self.scene.step()
            if (step + 1) % check_every == 0 and self._at_rest():
                return

    def settle_until_stable(self, window: float = 0.5, tolerance: float = 0.002, max_windows: int = 6) -> None:
        """Simulate in windows until no object moves more than ``tolerance`` m in one window;
        objects still moving after ``max_windows`` are removed (they would drift in the task)."""
        moving: list[sapien.Entity] = []
        for _ in range(max_windows):
            before = [a.get_pose().p.copy() for a in self.actors]
            for _step in range(int(window / _SIM_DT)):
                self.scene.step()
            moving = [a for a, p in zip(self.actors, before) if np.linalg.norm(a.get_pose().p - p) > tolerance]
            if not moving:
                return
        for actor in moving:
            self.remove(actor)
        self.settle(max_time=1.0)

    def _at_rest(self) -> bool:
        for actor in self.actors:
            body = actor.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent)
            if np.linalg.norm(body.linear_velocity) > 0.01 or np.linalg.norm(body.angular_velocity) > 0.1:
                return False
        return True

    def penetrates(self, actor: sapien.Entity, tolerance: float = 1e-3, keep_others: bool = False) -> bool:
        """Whether ``actor`` overlaps another object (contact with separation below -tolerance).

        The test takes one physics step; ``keep_others`` puts the other objects back where they were
        (that step would otherwise push them away from an overlapping newcomer)."""
        others = [a for a in self.actors if a is not actor]
        saved = [a.get_pose() for a in others] if keep_others else []
        self.scene.step()
        overlaps = False
        for contact in self.scene.get_contacts():
            entities = {contact.bodies[0].entity, contact.bodies[1].entity}
            if actor in entities and len(entities & set(self.actors)) == 2:
                if any(p.separation < -tolerance for p in contact.points):
                    overlaps = True
                    break
        for other, pose in zip(others, saved):
            other.set_pose(pose)
            body = other.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent)
            body.set_linear_velocity([0.0, 0.0, 0.0])
            body.set_angular_velocity([0.0, 0.0, 0.0])
        return overlaps


def _in_workspace(position: np.ndarray) -> bool:
    rel = position - WORKSPACE_CENTER
    return bool(np.all(np.abs(rel[:2]) <= WORKSPACE_HALF_SIZE) and -0.01 <= position[2] <= 2 * WORKSPACE_HALF_SIZE)


def generate_layout(
    object_set: ObjectSet,
    rng: np.random.Generator,
    scene_type: SceneType = "pile",
    num_objects: int | None = None,
    max_objects: int = 8,
) -> SceneGeometry:
    """A clutter layout per the VGN protocol.

    Args:
        object_set: where objects come from (procedural or a mesh folder).
        rng: the only source of randomness (same state -> same layout).
        scene_type: ``"pile"`` (dropped from 0.2 m into a box that is then removed),
            ``"packed"`` (upright objects placed side by side, rejected on overlap) or
            ``"packed_ycb"`` (the authors' validation scenes: :data:`PACKED_YCB_OBJECTS` distinct
            objects upright at scale 0.8, random yaw, x and y within 10 cm of the workspace centre,
            a placement rejected on contact, at most 12 attempts in all, at least 3 objects kept).
        num_objects: objects to try to place; ``None`` draws Poisson(4) + 1 (VGN), or 4 for ``packed_ycb``.
        max_objects: cap on the drawn count.

    Returns:
        The settled scene; objects that left the workspace are dropped. At least one
        object remains (the layout is redrawn otherwise).
    """
    if scene_type not in SCENE_TYPES:
        raise ValueError(f"unknown scene_type {scene_type!r}; expected one of {SCENE_TYPES}")
    if num_objects is not None and num_objects <= 0:
        raise ValueError(f"num_objects must be positive, got {num_objects}")
    if max_objects <= 0:
        raise ValueError(f"max_objects must be positive, got {max_objects}")
    for _ in range(20):
        if scene_type == "packed_ycb":
            count = num_objects if num_objects is not None else PACKED_YCB_OBJECTS
            layout = _packed_ycb(object_set, rng, count)
            if len(layout.objects) >= min(PACKED_YCB_MIN_OBJECTS, count):
                return layout
            continue
        count = num_objects if num_objects is not None else min(int(rng.poisson(4)) + 1, max_objects)
        layout = _pile(object_set, rng, count) if scene_type == "pile" else _packed(object_set, rng, count)
        if layout.objects:
            return layout
    raise RuntimeError("could not place any object in the workspace after 20 attempts")


def _pile(object_set: ObjectSet, rng: np.random.Generator, count: int) -> SceneGeometry:
    sim = _SettleScene()
    box_half = WORKSPACE_HALF_SIZE / 2
    sim.add_walls(WORKSPACE_CENTER, box_half)
    placed: list[tuple[ObjectGeometry, sapien.Entity]] = []
    for _ in range(count):
        obj = object_set.sample(rng, float(rng.uniform(0.8, 1.0)))
        pose = np.eye(4)
        pose[:3, :3] = _random_rotation(rng)
        xy = WORKSPACE_CENTER[:2] + rng.uniform(-box_half / 2, box_half / 2, size=2)
        pose[:3, 3] = [xy[0], xy[1], 0.2]
        placed.append((obj, sim.add(obj, pose)))
        sim.settle(max_time=1.0)
    sim.remove_walls()
    sim.settle(max_time=2.0)
    sim.settle_until_stable()
    return _collect(placed, sim)


def _packed(object_set: ObjectSet, rng: np.random.Generator, count: int) -> SceneGeometry:
    sim = _SettleScene()
    placed: list[tuple[ObjectGeometry, sapien.Entity]] = []
    half = 0.07
    for _ in range(count):
        obj = object_set.sample(rng, float(rng.uniform(0.7, 0.9)))
        for _attempt in range(12):
            pose = np.eye(4)
            pose[:3, :3] = _yaw(float(rng.uniform(0, 2 * np.pi)))
            xy = WORKSPACE_CENTER[:2] + rng.uniform(-half, half, size=2)
            pose[:3, 3] = [xy[0], xy[1], 0.002]
            actor = sim.add(obj, pose)
            if sim.penetrates(actor):
                sim.remove(actor)
                continue
            placed.append((obj, actor))
            break
    sim.settle(max_time=1.5)
    sim.settle_until_stable()
    return _collect(placed, sim)


def _distinct_objects(object_set: ObjectSet, rng: np.random.Generator, count: int,
                      scale: float) -> list[ObjectGeometry]:
    """``count`` objects with different names (fewer when the set runs out of names)."""
    if hasattr(object_set, "sample_distinct"):
        return object_set.sample_distinct(rng, count, scale)
    objects: dict[str, ObjectGeometry] = {}
    for _ in range(20 * count):
        obj = object_set.sample(rng, scale)
        objects.setdefault(obj.name, obj)
        if len(objects) == count:
            break
    return list(objects.values())


def _packed_ycb(object_set: ObjectSet, rng: np.random.Generator, count: int) -> SceneGeometry:
    sim = _SettleScene()
    placed: list[tuple[ObjectGeometry, sapien.Entity]] = []
    waiting = _distinct_objects(object_set, rng, count, PACKED_YCB_SCALE)
    for _attempt in range(PACKED_YCB_ATTEMPTS):
        if not waiting:
            break
        pose = np.eye(4)
        pose[:3, :3] = _yaw(float(rng.uniform(0, 2 * np.pi)))
        xy = WORKSPACE_CENTER[:2] + rng.uniform(-PACKED_YCB_HALF_RANGE, PACKED_YCB_HALF_RANGE, size=2)
        pose[:3, 3] = [xy[0], xy[1], 0.002]
        actor = sim.add(waiting[0], pose)
        if sim.penetrates(actor, tolerance=0.0, keep_others=True):
            sim.remove(actor)
            continue
        placed.append((waiting.pop(0), actor))
    sim.settle(max_time=1.5)
    sim.settle_until_stable()
    return _collect(placed, sim)


def _collect(placed: list[tuple[ObjectGeometry, sapien.Entity]], sim: _SettleScene) -> SceneGeometry:
    objects, poses = [], []
    for obj, actor in placed:
        if actor not in sim.actors:
            continue
        matrix = sapien_pose_to_matrix(actor.get_pose())
        centre = matrix[:3, :3] @ obj.collision_mesh().centroid + matrix[:3, 3]
        if _in_workspace(centre):
            objects.append(obj)
            poses.append(matrix)
    return SceneGeometry(objects=objects, object_poses=np.asarray(poses).reshape(-1, 4, 4))
