"""The cameras of ``GraspClutter-v1`` and the point cloud of its depth camera.

The depth camera looks at the workspace from the side opposite the robot (or from a per-scene
random pose on the upper hemisphere around it); its cloud drops the robot's pixels and is
cropped to the workspace above the table (world frame), voxel-downsampled and resampled to a
fixed size with a mask (:mod:`rtv3_maniskill.tasks.point_cloud`). The render camera is for
videos and the viewer.
"""

from __future__ import annotations

import numpy as np
import torch
from mani_skill.envs.utils.observations.observations import sensor_data_to_pointcloud
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils

from rtv3_maniskill.robot.scene_geometry import WORKSPACE_CENTER
from rtv3_maniskill.tasks.point_cloud import process_point_cloud

DEPTH_CAMERA = "depth_camera"
CLOUD_SEED_OFFSET = 104729
"""Added to the episode seed for the camera cloud's resampling stream (apart from the scene's)."""
CAMERA_SEED_OFFSET = 7919
"""Added to the episode seed for the random camera pose."""


def depth_camera_config(resolution: int, randomize: bool, episode_seed: int | None) -> CameraConfig:
    """The depth camera (``resolution`` square pixels, 50 deg field of view, 0.05-2 m).

    Fixed: 0.32 m behind and 0.30 m above the workspace centre; with ``randomize`` and a seed: at
    0.5-0.7 m, azimuth within +-90 deg of that side and elevation 35-65 deg, drawn from the seed.
    Looks at a point 6 cm above the table at the workspace centre.
    """
    eye = WORKSPACE_CENTER + np.array([0.32, 0.0, 0.30])
    if randomize and episode_seed is not None:
        rng = np.random.default_rng(int(episode_seed) + CAMERA_SEED_OFFSET)
        azimuth = rng.uniform(-np.pi / 2, np.pi / 2)
        elevation = rng.uniform(np.deg2rad(35), np.deg2rad(65))
        radius = rng.uniform(0.5, 0.7)
        eye = WORKSPACE_CENTER + radius * np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
    pose = sapien_utils.look_at(eye=eye.tolist(), target=[WORKSPACE_CENTER[0], WORKSPACE_CENTER[1], 0.06])
    return CameraConfig(DEPTH_CAMERA, pose, resolution, resolution, np.deg2rad(50), 0.05, 2.0)


def render_camera_config() -> CameraConfig:
    """The 512 x 512 render camera."""
    # From the front side and above: the arm reaches in from the side of the frame, not over the
    # workspace; the hand at the ready pose and the objects are both in view.
    pose = sapien_utils.look_at([WORKSPACE_CENTER[0] + 0.27, 0.42, 0.58], [WORKSPACE_CENTER[0] - 0.09, -0.02, 0.17])
    return CameraConfig("render_camera", pose, 512, 512, 0.85, 0.01, 100)


def robot_segmentation_ids(robot, device) -> torch.Tensor:
    """The sorted per-scene segmentation ids of the robot's visual bodies."""
    ids = [obj.entity.per_scene_id for link in robot.get_links() for obj in link._objs]
    return torch.as_tensor(sorted(set(ids)), device=device)


def capture_point_cloud(scene, robot, seeds, num_points: int, voxel_size: float,
                        device) -> tuple[torch.Tensor, torch.Tensor]:
    """Render the depth camera and process its cloud: ``(B, N, 6)`` xyz (world, m) + rgb, ``(B, N)`` mask.

    Keeps pixels on an actor other than the robot, in the workspace; the resampling of sub-scene i draws from
    ``seeds[i] + CLOUD_SEED_OFFSET``, so the same seed gives the same cloud.
    """
    camera = scene.sensors[DEPTH_CAMERA]
    scene.update_render(update_sensors=True, update_human_render_cameras=False)
    camera.capture()
    images = camera.get_obs(rgb=True, depth=False, position=True, segmentation=True)
    raw = sensor_data_to_pointcloud(
        dict(sensor_param={DEPTH_CAMERA: camera.get_params()}, sensor_data={DEPTH_CAMERA: images}),
        {DEPTH_CAMERA: camera},
    )["pointcloud"]
    xyz = raw["xyzw"][..., :3]
    rgb = raw["rgb"].float() / 255.0
    seg = raw["segmentation"][..., 0]
    keep = (seg != 0) & ~torch.isin(seg, robot_segmentation_ids(robot, device))
    generators = [torch.Generator().manual_seed(int(seed) + CLOUD_SEED_OFFSET) for seed in seeds]
    return process_point_cloud(xyz, rgb, keep, num_points, voxel_size, generators)
