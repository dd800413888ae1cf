"""Expert demonstrations: plan to a grasp candidate's pre-grasp, execute in the simulator, record.

For each grasp candidate of a scene (paper, "Simulation Setup and Data Collection"):

1. a collision-free start configuration from the authors' training distribution: the Panda
   ready pose plus per-joint Gaussian noise (:func:`random_start_configuration`), so that the
   prior learns around the state every shared-control trial starts from;
2. an OMPL/Pinocchio plan to the target's pre-grasp, and a check that the straight 5 cm
   approach to the grasp is feasible (``rtv3_maniskill.robot.planner``);
3. execution in ``GraspClutter-v1`` at 20 Hz with ``pd_joint_pos_vel`` control, then
   ``HOLD_STEPS`` steps holding the final pose (the model learns to stop, docs/PAPER_DETAILS.md). With
   ``end_at="pregrasp"`` (the paper's protocol: trajectories and users target the
   pre-grasp; the final approach is a separate user action) the demonstration ends at the
   pre-grasp; with ``end_at="grasp"`` the approach is executed too;
4. what the simulator did is recorded: per step the state (TCP pose, body twist, joint
   state) and, as the action, the body twist realised over the step.

Episodes are discarded, with the reason counted, on planning failure, a robot contact
while travelling to the pre-grasp, disturbing the scene during the approach, a joint
limit, or missing the pre-grasp.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from rtv3_maniskill import features
from rtv3_maniskill.robot.starts import random_start_configuration
from rtv3_maniskill.tasks.grasp_sampler import canonicalize_symmetric

HOLD_STEPS = 13
END_AT = ("pregrasp", "grasp")
"""Where a demonstration ends (see the module docstring)."""
FAILURE_REASONS = (
    "infeasible_target",  # no collision-free IK for the pre-grasp or the grasp: not a planner failure
    "planning_failed",
    "collision",
    "disturbed_target",  # the target object moved > 2 cm (pushed during the approach)
    "disturbed_scene",  # another object moved > 5 mm
    "joint_limit",
    "missed_pregrasp",
    "no_start_pose",
)
_INFEASIBLE = ("ik_failed", "goal_in_collision")
PREGRASP_POSITION_TOLERANCE = 0.01
START_ATTEMPTS = 10
"""Draws of the start distribution tried for a collision-free start before ``no_start_pose``."""
"""m: the executed motion must pass within this distance of the pre-grasp."""


@dataclass
class Episode:
    """One recorded demonstration (S steps, all float32 arrays, world frame)."""

    state: np.ndarray
    """``(S, 27)`` see ``rtv3_maniskill.features.STATE``."""
    action: np.ndarray
    """``(S, 6)`` body twist realised over each step."""
    point_cloud: np.ndarray
    """``(N, 6)`` static scene cloud (xyz + rgb)."""
    point_cloud_mask: np.ndarray
    grasps: np.ndarray
    """``(M, 9)`` padded grasp set."""
    grasps_mask: np.ndarray
    target_grasp_index: int
    scene_seed: int
    object_names: list[str]
    target_object: int
    task: str
    pregrasp_step: int
    """Index of the step at which the pre-grasp is reached (the approach starts)."""
    info: dict = field(default_factory=dict)
    history_prefix: np.ndarray | None = None
    """``(P, 27)`` states visited before ``state[0]`` (P < T), e.g. a DAgger rollout's: they enter the
    stored state histories of the first frames and are never frames (never action targets) themselves."""


def describe_grasp(object_name: str, grasp_pose: np.ndarray) -> str:
    """Task string, e.g. ``"grasp the mug from the top"`` (approach direction in the world)."""
    approach = grasp_pose[:3, 2]
    if approach[2] < -0.7:
        side = "the top"
    else:
        # The robot stands at -x: +x approach comes from the robot's side ("front").
        horizontal = approach[:2] / max(np.linalg.norm(approach[:2]), 1e-9)
        sides = {"the front": np.array([1.0, 0.0]), "the back": np.array([-1.0, 0.0]),
                 "the right": np.array([0.0, 1.0]), "the left": np.array([0.0, -1.0])}
        side = max(sides, key=lambda k: float(sides[k] @ horizontal))
    return f"grasp the {object_name} from {side}"


def state_vector(obs: dict) -> np.ndarray:
    """``observation.state (27,)`` of a single ``GraspClutter-v1`` observation, numpy float32."""
    return features.observation_from_env(obs)[features.STATE][0].cpu().numpy()


def draw_start(planner, rng: np.random.Generator) -> np.ndarray | None:
    """The first collision-free ``(7,)`` draw (rad) of the authors' start distribution for ``planner``'s
    scene in :data:`START_ATTEMPTS` tries, or None."""
    kin = planner.kin
    for _ in range(START_ATTEMPTS):
        q = random_start_configuration(rng, kin.lower + 1e-3, kin.upper - 1e-3)
        if planner.is_collision_free(q):
            return q
    return None


class DemonstrationRecorder:
    """Plans and executes demonstrations in one ``GraspClutter-v1`` env (``pd_joint_pos_vel``).

    ``context_obs_mode`` decides where the static point cloud comes from: ``"pointcloud"``
    renders the depth camera once per scene; ``"state_dict"`` samples the meshes.
    """

    def __init__(self, env, planner_factory, plan_timeout: float = 3.0, end_at: str = "pregrasp"):
        if end_at not in END_AT:
            raise ValueError(f"end_at must be one of {END_AT}, got {end_at!r}")
        self.end_at = end_at
        self.env = env
        self.base = env.unwrapped
        self.planner_factory = planner_factory
        self.plan_timeout = plan_timeout
        self.planner = None
        self.scene_seed: int | None = None
        self._context: dict[str, np.ndarray] = {}

    def load_scene(self, scene_seed: int) -> int:
        """Reset to the scene of ``scene_seed``; returns its number of grasp candidates."""
        obs, _ = self.env.reset(seed=scene_seed, options=dict(reconfigure=True))
        self.scene_seed = scene_seed
        extra = obs["extra"]
        if self.base.obs_mode == "pointcloud":
            cloud, mask = extra["point_cloud"][0], extra["point_cloud_mask"][0]
        else:
            cloud, mask = self.base.mesh_point_cloud[0], self.base.mesh_point_cloud_mask[0]
        self._context = dict(
            point_cloud=cloud.cpu().numpy().astype(np.float32),
            point_cloud_mask=mask.cpu().numpy().astype(np.float32),
            grasps=extra["grasps"][0].cpu().numpy().astype(np.float32),
            grasps_mask=extra["grasps_mask"][0].cpu().numpy().astype(np.float32),
        )
        self.planner = self.planner_factory(self.base.layouts[0])
        return int(self._context["grasps_mask"].sum())

    def set_scene_point_cloud(self, point_cloud, point_cloud_mask) -> None:
        """Record the loaded scene's episodes with this static cloud (e.g. a depth-camera
        capture) instead of the one :meth:`load_scene` took: ``(N, 6)`` and ``(N,)``."""
        if self.scene_seed is None:
            raise RuntimeError("load_scene first: the point cloud belongs to the loaded scene")
        cloud = np.asarray(point_cloud, dtype=np.float32)
        mask = np.asarray(point_cloud_mask, dtype=np.float32)
        if cloud.ndim != 2 or cloud.shape[1] != 6 or mask.shape != cloud.shape[:1]:
            raise ValueError(f"expected a (N, 6) cloud and a (N,) mask, got {cloud.shape} and {mask.shape}")
        self._context.update(point_cloud=cloud, point_cloud_mask=mask)

    def record(self, grasp_index: int, seed: int) -> Episode | str:
        """Demonstration toward grasp ``grasp_index`` of the loaded scene, or a failure reason."""
        q_start = draw_start(self.planner, np.random.default_rng(seed))
        if q_start is None:
            return "no_start_pose"
        return self.record_from(q_start, grasp_index, seed)

    def record_from(self, q_start: np.ndarray, grasp_index: int, seed: int) -> Episode | str:
        """Demonstration toward grasp ``grasp_index`` from the arm joints ``q_start`` ``(7,)`` (rad), or a
        failure reason: the expert's plan from a given state (DAgger relabelling starts here)."""
        grasp_set = self.base.grasp_sets[0]
        target_object = int(grasp_set.object_ids[grasp_index])
        q_start = np.asarray(q_start, dtype=np.float64)[:7]
        # Parallel-jaw symmetry: aim for the twin closer to the start orientation (docs/PAPER_DETAILS.md).
        grasp = canonicalize_symmetric(grasp_set.poses[grasp_index : grasp_index + 1],
                                       self.planner.forward_kinematics(q_start))[0]
        pregrasp = features.pregrasp_poses(torch.from_numpy(grasp)).numpy()
        transit = self.planner.plan_to_pose(q_start, pregrasp, timeout=self.plan_timeout, seed=seed)
        if not transit.success:
            return "infeasible_target" if transit.failure_reason in _INFEASIBLE else "planning_failed"
        approach = self.planner.plan_straight_line(transit.trajectory.q[-1], grasp, ignore_objects={target_object})
        if not approach.success:
            return "infeasible_target" if approach.failure_reason in _INFEASIBLE else "planning_failed"
        return self._execute(transit.trajectory, approach.trajectory, grasp_index, target_object, grasp, pregrasp, seed)

    def _execute(self, transit, approach, grasp_index, target_object, grasp, pregrasp, seed) -> Episode | str:
        """Run the planned motion toward ``grasp`` (``(4, 4)``, the canonicalised target pose)."""
        if self.end_at == "grasp":
            q_plan = np.concatenate([transit.q, approach.q[1:]])
            qd_plan = np.concatenate([transit.qd, approach.qd[1:]])
        else:
            q_plan, qd_plan = transit.q, transit.qd
        q_plan = np.concatenate([q_plan, np.repeat(q_plan[-1:], HOLD_STEPS, 0)])
        qd_plan = np.concatenate([qd_plan, np.zeros((HOLD_STEPS, 7))])
        pregrasp_step = len(transit.q) - 1
        obs, _ = self.env.reset(
            options=dict(reconfigure=False, init_qpos=transit.q[0], target_grasp_index=grasp_index)
        )
        object_poses_start = [a.pose.raw_pose.clone() for a in self.base.objects[0]]
        limits = self.base.agent.robot.get_qlimits()[0, :7].cpu().numpy()
        states, actions = [state_vector(obs)], []
        closest_to_pregrasp = np.inf
        pregrasp_t = torch.as_tensor(pregrasp, dtype=torch.float32)
        for k in range(1, len(q_plan)):
            action = np.concatenate([q_plan[k], qd_plan[k], [0.04]]).astype(np.float32)
            obs, _, _, _, info = self.env.step(torch.as_tensor(action)[None])
            states.append(state_vector(obs))
            actions.append(states[-1][7:13])  # realised body twist of this step
            if k <= pregrasp_step and bool(info["collision"]):
                return "collision"
            qpos = obs["agent"]["qpos"][0, :7].cpu().numpy()
            if np.any(qpos < limits[:, 0] + 1e-3) or np.any(qpos > limits[:, 1] - 1e-3):
                return "joint_limit"
            tcp = self.base.tcp_pose_matrix[0]
            closest_to_pregrasp = min(closest_to_pregrasp, float((tcp[:3, 3] - pregrasp_t[:3, 3]).norm()))
        for j, (actor, start) in enumerate(zip(self.base.objects[0], object_poses_start)):
            moved = float((actor.pose.raw_pose[0, :3] - start[0, :3]).norm())
            if j == target_object and moved > 0.02:
                return "disturbed_target"
            if j != target_object and moved > 0.005:
                return "disturbed_scene"
        if closest_to_pregrasp > PREGRASP_POSITION_TOLERANCE:
            return "missed_pregrasp"
        # The last state has no next step: its action is the zero twist of holding still.
        actions.append(np.zeros(6, dtype=np.float32))
        layout = self.base.layouts[0]
        names = [o.name for o in layout.objects]
        return Episode(
            state=np.stack(states),
            action=np.stack(actions).astype(np.float32),
            target_grasp_index=grasp_index,
            scene_seed=int(self.scene_seed),
            object_names=names,
            target_object=target_object,
            task=describe_grasp(names[target_object], grasp),
            pregrasp_step=pregrasp_step,
            info=dict(plan_seed=seed, closest_to_pregrasp=closest_to_pregrasp, end_at=self.end_at),
            **self._context,
        )


__all__ = ["DemonstrationRecorder", "END_AT", "Episode", "FAILURE_REASONS", "HOLD_STEPS", "describe_grasp"]
