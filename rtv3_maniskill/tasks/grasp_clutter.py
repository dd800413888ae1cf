"""``GraspClutter-v1``: reach a grasp candidate's pre-grasp in a cluttered table scene.

The scene: ManiSkill's Panda (``panda_twist``: every Panda control mode plus
``pd_ee_twist``) on the table, a VGN-style clutter of procedural or mesh-folder
objects in the 30 cm workspace cube, and up to ``max_grasps`` collision-free antipodal
grasp candidates per scene. Each episode picks a target grasp (privileged, in ``info``;
settable with ``reset(options={"target_grasp_index": ...})``); success is reaching its
pre-grasp (5 cm back along the approach axis) within the paper's pose distance.

Observations (every mode has the same ``extra`` keys; ``B = num_envs``):

* ``agent``: ``qpos (B, 9)``, ``qvel (B, 9)`` (arm + fingers);
* ``extra.tcp_pose (B, 7)``: TCP position + wxyz quaternion, world frame;
* ``extra.tcp_twist (B, 6)``: TCP body twist realised over the last control step;
* ``extra.grasps (B, M, 9)`` / ``extra.grasps_mask (B, M)``: see ``rtv3_maniskill.features``;
* ``extra.point_cloud (B, N, 6)`` / ``extra.point_cloud_mask (B, N)``: xyz (world) + rgb,
  from the depth camera with ``obs_mode="pointcloud"``, else sampled from the object meshes.

The task class keeps ManiSkill's hooks; the scene building is in
:mod:`~rtv3_maniskill.tasks.clutter_scene`, the cameras and the depth camera's cloud in
:mod:`~rtv3_maniskill.tasks.cameras`, what the robot touches in
:mod:`~rtv3_maniskill.tasks.robot_contacts`.

Layouts are computed per sub-scene from the episode seed, so the same seed gives the
same scene and grasps; with ``num_envs > 1`` (GPU backend) every sub-scene has its own
clutter and partial resets (``options={"env_idx": ...}``) keep it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import sapien
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.registration import register_env
from mani_skill.utils.scene_builder.table import TableSceneBuilder
from mani_skill.utils.structs.types import SimConfig

from rtv3_maniskill import se3
from rtv3_maniskill.features import DEFAULT_MAX_GRASPS, DEFAULT_NUM_POINTS, FPS, GRASP_DIM, pregrasp_poses
from rtv3_maniskill.robot.execution import EXECUTIONS
from rtv3_maniskill.robot.scene_geometry import READY_QPOS, ROBOT_BASE_POSITION, SceneGeometry
from rtv3_maniskill.robot.twist_controller import PandaTwist, set_execution  # noqa: F401  (registers)
from rtv3_maniskill.tasks import cameras
from rtv3_maniskill.tasks.clutter_scene import (
    build_object,
    build_pedestal,
    generate_scene,
    sample_mesh_point_cloud,
    table_pose,
)
from rtv3_maniskill.tasks.grasp_set import GraspSet
from rtv3_maniskill.tasks.object_library import make_object_set
from rtv3_maniskill.tasks.point_cloud import DEFAULT_VOXEL_SIZE
from rtv3_maniskill.tasks.robot_contacts import BASE_LINK, RobotContactPairs
from rtv3_maniskill.tasks.scene_generation import SCENE_TYPES, matrix_to_sapien_pose

START_QPOS = np.concatenate([READY_QPOS, [0.04, 0.04]])
"""Default start (arm + open fingers): the ready pose, plus N(0, 0.02) per joint at reset."""


@register_env("GraspClutter-v1", max_episode_steps=150)
class GraspClutterEnv(BaseEnv):
    """Reach the target grasp's pre-grasp pose in clutter (RT-V3 simulation setup).

    Args (besides ManiSkill's ``obs_mode``, ``control_mode``, ``num_envs``, ...):
        scene_type: ``"pile"``, ``"packed"`` or ``"mixed"`` (each scene draws one).
        num_objects: objects per scene; ``None`` draws Poisson(4) + 1 (VGN).
        object_source: ``"procedural"``, ``"procedural:box,mug"`` or a folder of meshes.
        max_grasps: M, grasp candidates kept per scene (padded with a mask).
        num_points: N, points per cloud (padded with a mask).
        voxel_size: point-cloud voxel size in m (7.5 mm).
        camera_resolution: depth camera width = height in pixels.
        randomize_camera: draw the camera pose per scene (paper) instead of a fixed view.
        success_threshold: pose distance (docs/PAPER_DETAILS.md, shared-control weights) counted as success.
        collision_force_threshold: N of contact force on any robot link counted as collision.
        execution: how ``pd_ee_twist`` executes a twist (``twist_controller.EXECUTIONS``): ``"capped"``
            (as commanded, up to 0.3 m/s and 1.2 rad/s) or ``"tracked"`` (the authors': 0.75 of the
            command per step, no practical cap).
        self_contacts: count a robot link touching another as a collision (the authors' simulator
            never reports them: False reproduces their rule).
    """

    SUPPORTED_ROBOTS = ["panda_twist"]
    SUPPORTED_OBS_MODES = ("state", "state_dict", "pointcloud", "none")

    def __init__(
        self,
        *args,
        robot_uids: str = "panda_twist",
        scene_type: str = "pile",
        num_objects: int | None = None,
        object_source: str = "procedural",
        max_grasps: int = DEFAULT_MAX_GRASPS,
        num_points: int = DEFAULT_NUM_POINTS,
        voxel_size: float = DEFAULT_VOXEL_SIZE,
        camera_resolution: int = 128,
        randomize_camera: bool = False,
        success_threshold: float = 0.1,
        collision_force_threshold: float = 1e-2,
        execution: str = "capped",
        self_contacts: bool = True,
        reconfiguration_freq: int | None = None,
        **kwargs,
    ):
        if scene_type not in (*SCENE_TYPES, "mixed"):
            raise ValueError(f"unknown scene_type {scene_type!r}; expected one of {(*SCENE_TYPES, 'mixed')}")
        if num_objects is not None and num_objects <= 0:
            raise ValueError(f"num_objects must be positive or None, got {num_objects}")
        for name, value in (("max_grasps", max_grasps), ("num_points", num_points),
                            ("camera_resolution", camera_resolution)):
            if value <= 0:
                raise ValueError(f"{name} must be positive, got {value}")
        if execution not in EXECUTIONS:
            raise ValueError(f"unknown execution {execution!r}; expected one of {tuple(EXECUTIONS)}")
        if voxel_size <= 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        obs_mode = kwargs.get("obs_mode", "state")
        if obs_mode is not None and obs_mode not in self.SUPPORTED_OBS_MODES:
            raise ValueError(f"unsupported obs_mode {obs_mode!r} for GraspClutter-v1; "
                             f"expected one of {self.SUPPORTED_OBS_MODES}")
        self.scene_type = scene_type
        self.num_objects = num_objects
        self.object_set = make_object_set(object_source)  # raises on a missing / empty folder
        self.max_grasps = max_grasps
        self.num_points = num_points
        self.voxel_size = voxel_size
        self.camera_resolution = camera_resolution
        self.randomize_camera = randomize_camera
        self.success_threshold = success_threshold
        self.collision_force_threshold = collision_force_threshold
        self.execution = execution
        self.self_contacts = bool(self_contacts)
        num_envs = kwargs.get("num_envs", 1)
        if reconfiguration_freq is None:
            # A new clutter every episode on one env; fixed clutter per sub-scene when batched.
            reconfiguration_freq = 1 if num_envs == 1 else 0
        self.layouts: list[SceneGeometry] = []
        self.grasp_sets: list[GraspSet] = []
        super().__init__(*args, robot_uids=robot_uids, reconfiguration_freq=reconfiguration_freq, **kwargs)

    # ------------------------------------------------------------------ configuration

    @property
    def _default_sim_config(self):
        return SimConfig(sim_freq=100, control_freq=FPS)

    @property
    def _default_sensor_configs(self):
        seed = int(self._episode_seed[0]) if self._episode_seed is not None else None
        return [cameras.depth_camera_config(self.camera_resolution, self.randomize_camera, seed)]

    @property
    def _default_human_render_camera_configs(self):
        return cameras.render_camera_config()

    # ------------------------------------------------------------------ loading

    def _load_agent(self, options: dict):
        super()._load_agent(options, sapien.Pose(p=ROBOT_BASE_POSITION.tolist()))
        set_execution(self.agent, self.execution)

    def _load_scene(self, options: dict):
        self._contact_links = None
        self._contact_pairs = None  # robot_contact_kinds' body pairs (and GPU query) belong to this scene
        self.table_scene = TableSceneBuilder(self, robot_init_qpos_noise=0.0)
        self.table_scene.build()
        self.table_scene.table.set_pose(table_pose(self.table_scene.table_height))
        if self.scene.can_render():
            build_pedestal(self.scene, self.table_scene.table_height)
        self.layouts, self.grasp_sets, self.objects = [], [], []
        grasps = torch.zeros(self.num_envs, self.max_grasps, GRASP_DIM)
        grasps_mask = torch.zeros(self.num_envs, self.max_grasps)
        surface_clouds, surface_masks = [], []
        material = sapien.physx.PhysxMaterial(0.6, 0.5, 0.0)
        for i in range(self.num_envs):
            rng = np.random.default_rng(int(self._episode_seed[i]))
            layout, grasp_set = generate_scene(self.object_set, rng, self.scene_type, self.num_objects,
                                               self.max_grasps)
            self.layouts.append(layout)
            self.grasp_sets.append(grasp_set)
            padded, mask = grasp_set.to_padded(self.max_grasps)
            grasps[i], grasps_mask[i] = torch.from_numpy(padded), torch.from_numpy(mask)
            self.objects.append(
                [build_object(self.scene, obj, pose, i, j, material)
                 for j, (obj, pose) in enumerate(zip(layout.objects, layout.object_poses))]
            )
            cloud, cloud_mask = sample_mesh_point_cloud(layout, rng, int(self._episode_seed[i]), self.num_points,
                                                 self.voxel_size)
            surface_clouds.append(cloud)
            surface_masks.append(cloud_mask)
        self.grasps = grasps.to(self.device)
        self.grasps_mask = grasps_mask.to(self.device)
        self.grasp_poses = se3.pose_to_matrix(self.grasps[..., :3], self.grasps[..., 3:7])  # (B, M, 4, 4)
        self.mesh_point_cloud = torch.stack(surface_clouds).to(self.device)
        self.mesh_point_cloud_mask = torch.stack(surface_masks).to(self.device)
        self.target_grasp_index = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self._prev_tcp_pose = None
        self._tcp_twist = torch.zeros(self.num_envs, 6, device=self.device)

    # ------------------------------------------------------------------ episodes

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        with torch.device(self.device):
            b = len(env_idx)
            self.table_scene.table.set_pose(table_pose(self.table_scene.table_height))
            # Objects back to their settled layout poses, at rest.
            for i in env_idx.tolist():
                for actor, pose in zip(self.objects[i], self.layouts[i].object_poses):
                    actor.set_pose(matrix_to_sapien_pose(pose))
                    actor.set_linear_velocity(torch.zeros(1, 3))
                    actor.set_angular_velocity(torch.zeros(1, 3))
            qpos = options.get("init_qpos")
            if qpos is None:  # the ready pose, slightly perturbed
                noise = torch.as_tensor(self._batched_episode_rng[env_idx].normal(0, 0.02, 9), dtype=torch.float32)
                qpos = torch.as_tensor(START_QPOS, dtype=torch.float32) + noise.reshape(b, 9)
            else:
                qpos = (torch.as_tensor(qpos, dtype=torch.float32).reshape(-1, torch.as_tensor(qpos).shape[-1])
                        .expand(b, -1).clone())
                if qpos.shape[-1] == 7:
                    qpos = torch.cat([qpos, torch.full((b, 2), 0.04)], -1)
                if qpos.shape[-1] != 9 or not torch.isfinite(qpos).all():
                    raise ValueError("options['init_qpos'] must be finite with 7 or 9 joint values, "
                                     f"got shape {tuple(qpos.shape)}")
            qpos[:, 7:] = 0.04
            self.agent.reset(qpos)
            self.agent.robot.set_pose(sapien.Pose(p=ROBOT_BASE_POSITION.tolist()))
            self._set_target(env_idx, options.get("target_grasp_index"))
            self._tcp_twist[env_idx] = 0.0
            self._prev_tcp_pose = None

    def _set_target(self, env_idx: torch.Tensor, requested: Any) -> None:
        counts = self.grasps_mask[env_idx].sum(-1).long()
        if requested is None:
            draws = torch.as_tensor(self._batched_episode_rng[env_idx].random_sample(), dtype=torch.float32,
                                    device=self.device)
            index = (draws.reshape(-1) * counts).long().clamp(max=counts - 1)
        else:
            values = np.asarray(requested).reshape(-1)
            if values.dtype.kind not in "iuf" or not np.all(np.isfinite(values)) or np.any(values != np.round(values)):
                raise ValueError(f"target_grasp_index must be a whole number (or one per sub-scene), got {requested!r}")
            index = torch.as_tensor(values.astype(np.int64), device=self.device).expand(len(env_idx))
            bad = (index < 0) | (index >= counts)
            if bad.any():
                raise ValueError(
                    f"target_grasp_index {index[bad].tolist()} out of range: "
                    f"scenes have {counts[bad].tolist()} grasp candidates"
                )
        self.target_grasp_index[env_idx] = index

    # ------------------------------------------------------------------ stepping and observations

    def step(self, action):
        if isinstance(action, (torch.Tensor, np.ndarray, list, tuple)):
            values = torch.as_tensor(np.asarray(action, dtype=np.float32) if not isinstance(action, torch.Tensor)
                                     else action)
            if not torch.isfinite(values).all():
                raise ValueError(f"action contains NaN or inf: {values.tolist()}")
        return super().step(action)

    def _before_control_step(self):
        self._prev_tcp_pose = self.tcp_pose_matrix

    def _after_control_step(self):
        if self.gpu_sim_enabled:
            self.scene._gpu_fetch_all()
        if self._prev_tcp_pose is not None:
            self._tcp_twist = se3.body_twist(self._prev_tcp_pose, self.tcp_pose_matrix, 1.0 / self.control_freq)
            self._prev_tcp_pose = None

    def _get_obs_extra(self, info: dict):
        pose = self.agent.tcp.pose
        extra = dict(
            tcp_pose=torch.cat([pose.p, pose.q], -1),
            tcp_twist=self._tcp_twist.clone(),
            grasps=self.grasps.clone(),
            grasps_mask=self.grasps_mask.clone(),
        )
        if self.obs_mode == "pointcloud":
            extra["point_cloud"], extra["point_cloud_mask"] = self.capture_point_cloud()
        else:
            extra["point_cloud"], extra["point_cloud_mask"] = (self.mesh_point_cloud.clone(),
                                                               self.mesh_point_cloud_mask.clone())
        if self.obs_mode == "state":
            # ManiSkill flattens "state" observations into one vector per env.
            extra = {key: value.reshape(self.num_envs, -1) for key, value in extra.items()}
        return extra

    def get_obs(self, info: dict | None = None, unflattened: bool = False):
        if self.obs_mode == "pointcloud":
            # The processed cloud lives in `extra`; ManiSkill's raw per-pixel cloud is not returned.
            info = self.get_info() if info is None else info
            return dict(agent=self._get_obs_agent(), extra=self._get_obs_extra(info))
        return super().get_obs(info, unflattened)

    # ------------------------------------------------------------------ success, collision and reward

    def evaluate(self) -> dict:
        distance = self.pregrasp_distance()
        success = distance < self.success_threshold
        return dict(
            success=success,
            is_success=success,
            collision=self.robot_in_collision(),
            pregrasp_distance=distance,
            target_grasp_index=self.target_grasp_index.clone(),
            target_pregrasp_pose=se3.matrix_to_pose(self.target_pregrasp_pose),
        )

    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return 1.0 - torch.tanh(5.0 * info["pregrasp_distance"]) - info["collision"].float()

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return self.compute_dense_reward(obs, action, info) / 1.0

    # ------------------------------------------------------------------ task quantities

    @property
    def tcp_pose_matrix(self) -> torch.Tensor:
        """``(B, 4, 4)`` TCP pose in the world frame."""
        pose = self.agent.tcp.pose
        return se3.pose_to_matrix(pose.p, pose.q)

    @property
    def target_grasp_pose(self) -> torch.Tensor:
        """``(B, 4, 4)`` the target grasp (TCP at the grasp)."""
        return self.grasp_poses[torch.arange(self.num_envs, device=self.device), self.target_grasp_index]

    @property
    def target_pregrasp_pose(self) -> torch.Tensor:
        """``(B, 4, 4)`` the target grasp moved ``PREGRASP_DISTANCE`` back along its approach (z) axis."""
        return pregrasp_poses(self.target_grasp_pose)

    def pregrasp_distance(self) -> torch.Tensor:
        """``(B,)`` pose distance (docs/PAPER_DETAILS.md, shared-control weights) of the TCP to the pre-grasp,
        the smaller over the grasp and its pi-about-z twin (parallel-jaw symmetry)."""
        return se3.symmetric_pose_distance(self.target_pregrasp_pose, self.tcp_pose_matrix,
                                           se3.SHARED_CONTROL_ROT_WEIGHT)

    def robot_in_collision(self) -> torch.Tensor:
        """``(B,)`` bool: any robot link but the base touches something with force above threshold (with
        ``self_contacts=False``, something other than another robot link)."""
        if getattr(self, "_contact_links", None) is None:
            self._contact_links = [link.name for link in self.agent.robot.get_links() if link.name != BASE_LINK]
        forces = self.agent.robot.get_net_contact_forces(self._contact_links)
        touching = (forces.norm(dim=-1) > self.collision_force_threshold).any(-1)
        if not self.self_contacts and bool(touching.any()):  # a contact of links only among themselves is none
            kinds = self.robot_contact_kinds()
            touching = touching & torch.as_tensor([bool(k - {"self"}) for k in kinds], device=touching.device)
        return touching

    def robot_contact_kinds(self) -> list[set[str]]:
        """What the robot touches now, per sub-scene: a subset of ``{"table", "object", "self"}``
        ("self": one robot link against another; the base, ``panda_link0``, is left out as in
        ``robot_in_collision``). Read it at a step where ``robot_in_collision`` holds, to say what the
        contact was. CPU: one pass over the contact list; GPU: one contact-pair impulse query."""
        if self._contact_pairs is None:
            self._contact_pairs = RobotContactPairs.build(self.agent.robot.get_links(), self.table_scene.table,
                                                          self.objects)
        return self._contact_pairs.touching_kinds(self.scene)

    def capture_point_cloud(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Render the depth camera and process its cloud: ``(B, N, 6)``, ``(B, N)``.

        Works in every observation mode (e.g. to grab a static scene cloud once per
        scene while stepping in ``state_dict`` mode).
        """
        # The resampling draws from the episode's seed: the same seed gives the same cloud.
        seeds = self._episode_seed if self._episode_seed is not None else [0] * self.num_envs
        return cameras.capture_point_cloud(self.scene, self.agent.robot, seeds, self.num_points, self.voxel_size,
                                           self.device)
