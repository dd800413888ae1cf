"""Building one ``GraspClutter-v1`` sub-scene: the clutter layout and its grasps, the SAPIEN actors,
and the point cloud sampled from the object meshes.

World frame: the table top at z = 0, the robot base at ``ROBOT_BASE_POSITION``; object poses are
world-from-object ``(4, 4)``. Everything is drawn from the caller's seeded generator, in a fixed
order, so a seed gives the same scene.
"""

from __future__ import annotations

import numpy as np
import sapien
import torch

from rtv3_maniskill.robot.scene_geometry import ROBOT_BASE_POSITION, TABLE_TOP_CENTER, SceneGeometry
from rtv3_maniskill.tasks.convex_cache import convex_part_file
from rtv3_maniskill.tasks.grasp_sampler import sample_grasps
from rtv3_maniskill.tasks.grasp_set import GraspSet
from rtv3_maniskill.tasks.object_library import ObjectSet
from rtv3_maniskill.tasks.point_cloud import process_point_cloud, sample_scene_surface
from rtv3_maniskill.tasks.scene_generation import (
    SCENE_TYPES,
    add_collision_shapes,
    generate_layout,
    matrix_to_sapien_pose,
)

SCENE_ATTEMPTS = 20
"""Layouts drawn (from the same generator) before giving up on finding one with a grasp candidate."""


def generate_scene(object_set: ObjectSet, rng: np.random.Generator, scene_type: str, num_objects: int | None,
                   max_grasps: int) -> tuple[SceneGeometry, GraspSet]:
    """A layout with at least one grasp candidate (redrawn from the same ``rng`` otherwise).

    ``scene_type``: one of ``SCENE_TYPES`` or ``"mixed"`` (each layout draws pile or packed);
    ``num_objects``: None draws the layout's own count. At most ``max_grasps`` candidates, checked
    with the gripper fully open (0.08 m).
    """
    for _ in range(SCENE_ATTEMPTS):
        kind = scene_type if scene_type != "mixed" else SCENE_TYPES[int(rng.integers(2))]
        layout = generate_layout(object_set, rng, kind, num_objects)
        # The gripper stays fully open (0.08 m): check hand collisions at that opening.
        grasp_set = sample_grasps(layout, rng, max_grasps=max_grasps, finger_clearance=0.04)
        if len(grasp_set.scores) > 0:
            return layout, grasp_set
    raise RuntimeError(f"no graspable clutter scene found in {SCENE_ATTEMPTS} layouts; check the object set")


def table_pose(table_height: float) -> sapien.Pose:
    """ManiSkill's table moved so that its top is ``TABLE_TOP_CENTER``'s slab (near edge clear of the robot)."""
    return sapien.Pose(p=[float(TABLE_TOP_CENTER[0]), 0.0, -table_height], q=[np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])


def build_pedestal(scene, table_height: float) -> None:
    """A visual column from the floor (``-table_height``) to the robot base (which stands below the table top)."""
    builder = scene.create_actor_builder()
    floor = -table_height
    half = (ROBOT_BASE_POSITION[2] - floor) / 2
    material = sapien.render.RenderMaterial(base_color=[0.3, 0.3, 0.32, 1.0])
    builder.add_box_visual(half_size=[0.12, 0.12, half], material=material)
    builder.initial_pose = sapien.Pose(p=[float(ROBOT_BASE_POSITION[0]) - 0.04, 0.0, floor + half])
    builder.build_kinematic(name="robot_pedestal")


def build_object(scene, obj, pose: np.ndarray, env: int, index: int, material):
    """The dynamic actor of object ``index`` of sub-scene ``env`` at world pose ``pose (4, 4)``.

    Collision: the object's convex parts with ``material``; visuals (when the scene renders): the
    mesh file of a mesh-folder object, else one primitive or convex-part mesh per part.
    """
    builder = scene.create_actor_builder()
    add_collision_shapes(builder, obj.shapes, material, obj.density)
    if scene.can_render():
        color = sapien.render.RenderMaterial(base_color=list(obj.color))
        if obj.mesh_file is not None:
            builder.add_visual_from_file(
                obj.mesh_file, sapien.Pose(p=obj.mesh_offset.tolist()), scale=[obj.mesh_scale] * 3
            )
        else:
            for shape in obj.shapes:
                local = matrix_to_sapien_pose(shape.local_pose)
                if shape.kind == "box":
                    builder.add_box_visual(local, half_size=shape.params, material=color)
                elif shape.kind == "sphere":
                    builder.add_sphere_visual(local, radius=shape.params[0], material=color)
                elif shape.kind == "cylinder":
                    builder.add_cylinder_visual(local, radius=shape.params[0], half_length=shape.params[1],
                                                material=color)
                elif shape.kind == "capsule":
                    builder.add_capsule_visual(local, radius=shape.params[0], half_length=shape.params[1],
                                               material=color)
                else:
                    builder.add_visual_from_file(convex_part_file(shape.vertices), local, material=color)
    builder.set_scene_idxs([env])
    builder.initial_pose = matrix_to_sapien_pose(pose)
    return builder.build(name=f"env{env}-object{index}-{obj.name}")


def sample_mesh_point_cloud(layout: SceneGeometry, rng: np.random.Generator, seed: int, num_points: int,
                     voxel_size: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The scene cloud sampled from the object meshes: ``(N, 6)`` xyz (world, m) + rgb and ``(N,)`` mask.

    Surface points come from ``rng``; the voxel-grid resampling to ``num_points`` from ``seed``.
    """
    surface = torch.from_numpy(sample_scene_surface(layout, rng)).float()[None]
    generator = torch.Generator().manual_seed(int(seed))
    keep = torch.ones(surface.shape[:2], dtype=torch.bool)
    cloud, cloud_mask = process_point_cloud(surface[..., :3], surface[..., 3:], keep, num_points, voxel_size,
                                            [generator])
    return cloud[0], cloud_mask[0]
