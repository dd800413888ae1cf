"""DAgger with the motion planner as the expert: demonstrations from the states the prior meets.

Behaviour cloning on planner demonstrations alone compounds its errors in the closed loop: the
prior drifts to states no demonstration visits, and stalls or runs into the clutter there. This
module collects data where the prior will be (Ross et al.'s DAgger, the planner as the expert):

1. **Roll out** a driver on a training scene towards a target grasp: the prior alone (its most
   likely twist, target-only context, from the authors' start distribution, as in the planning
   benchmark), or a simulated user through Direct teleoperation or through RT-V3 shared control
   (from the Panda ready pose, as in the shared-control benchmark). The rollout stops at the
   pre-grasp, at the first robot contact or after ``max_steps``.
2. **Relabel**: at a few visited states, re-plan from the current joint state to the target's
   pre-grasp (:meth:`DemonstrationRecorder.record_from`: OMPL + Pinocchio, executed in the
   simulator, the same checks as ``rtv3 generate``).
3. **Store** one demonstration per relabelled state: its first frame is the visited state (with
   the rollout's own velocity), its stored state history holds what happened before it in the
   rollout, the user's noise and lag included (``Episode.history_prefix``), and its actions are
   the expert's. A rollout's own frames are never action targets: they only appear inside the
   history of the first frames.

Rounds: train, roll out with the new checkpoint, relabel, train again on the union (the datasets
are merged with LeRobot's ``merge_datasets`` through ``rtv3 merge``; ``scripts/train_shipped_checkpoint.sh``
runs one round with Direct-driven users).

Output: a folder laid out like ``rtv3 generate``'s (``rtv3_staging/`` with ``attempts.csv`` and
one ``.npz`` per relabelled state, then the LeRobot dataset), resumable: a rerun skips finished
rollouts and relabels. Keys: ``scene..._grasp..._r{driver}`` for a rollout (its outcome), and
``scene..._grasp..._r{driver}t{step}`` for a relabel.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections import Counter
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

from rtv3_maniskill import ENV_ID, features
from rtv3_maniskill.benchmarks.episodes import SharedControlEnv, controller_speed_limits
from rtv3_maniskill.benchmarks.goals import check_scene_goals
from rtv3_maniskill.datagen.dagger_config import FAILURE_WINDOW_STEPS, DaggerConfig, parse_driver
from rtv3_maniskill.datagen.demonstrations import DemonstrationRecorder, state_vector
from rtv3_maniskill.datagen.lerobot_export import StagedScene, StagingArea, export_lerobot_dataset
from rtv3_maniskill.features import context_mask
from rtv3_maniskill.policies.rtv3.checkpoints import load_policy, resolve_checkpoint
from rtv3_maniskill.records import claim_folder, scene_seeds, select_targets
from rtv3_maniskill.robot.planner import PandaPlanner
from rtv3_maniskill.robot.planner_config import with_clearance
from rtv3_maniskill.robot.scene_geometry import READY_QPOS
from rtv3_maniskill.robot.starts import random_start_configuration
from rtv3_maniskill.scene_pool import run_scenes
from rtv3_maniskill.shared_control.config import SharedControlConfig
from rtv3_maniskill.shared_control.methods import make_method
from rtv3_maniskill.shared_control.simulated_users import make_user

DAGGER_SALT = 13
"""``select_targets`` salt of DAgger runs (targets drawn independently of generation and benchmarks)."""


@dataclass
class Rollout:
    """What one driver did: ``S + 1`` states (start included) and how it ended."""

    states: np.ndarray
    """``(S + 1, 27)`` ``observation.state`` per step (world frame)."""
    qpos: np.ndarray
    """``(S + 1, 7)`` arm joints (rad)."""
    outcome: str
    """``"success"``, ``"collision"`` or ``"timeout"``."""
    steps: int = 0
    info: dict = field(default_factory=dict)
    distances: np.ndarray | None = None
    """``(S + 1,)`` pose distance of the TCP to the target's pre-grasp per state (shared-control weights)."""


def relabel_steps(rollout: Rollout, count: int, min_step: int, rng: np.random.Generator,
                  failure_count: int = 0, failure_window: str = "last") -> list[int]:
    """Visited steps to re-plan from: ``count`` of ``min_step .. S`` (the state after a contact
    excluded), drawn one per equal stretch of the rollout so they spread over it; sorted.
    With ``failure_count`` > 0, a failed rollout gets that many instead, spread over a window of
    :data:`FAILURE_WINDOW_STEPS` steps: its last ones (``failure_window="last"``), or those from its
    closest approach to the pre-grasp on (``"drift"``, which needs ``rollout.distances``)."""
    last = rollout.steps - (1 if rollout.outcome == "collision" else 0)
    candidates = np.arange(min_step, last + 1)
    if failure_count > 0 and rollout.outcome != "success" and len(candidates):
        end = last
        if failure_window == "drift":
            if rollout.distances is None:
                raise ValueError("failure_window 'drift' needs the rollout's distances to the pre-grasp")
            closest = min_step + int(np.argmin(rollout.distances[min_step : last + 1]))
            end = min(closest + FAILURE_WINDOW_STEPS - 1, last)
        candidates, count = candidates[candidates <= end][-FAILURE_WINDOW_STEPS:], failure_count
    if len(candidates) == 0:
        return []
    if len(candidates) <= count:
        return candidates.tolist()
    stretches = np.array_split(candidates, count)
    return sorted(int(rng.choice(s)) for s in stretches)


class DaggerCollector:
    """The rollout env (``pd_ee_twist``, rendered context), the expert (a :class:`DemonstrationRecorder`
    in its own ``pd_joint_pos_vel`` env) and the policy, for one process."""

    def __init__(self, config: DaggerConfig, policy: Any) -> None:
        self.config = config
        self.policy = policy
        sizes = dict(num_points=int(policy.config.num_points), max_grasps=int(policy.config.max_grasps),
                     scene_type=config.scene_type, object_source=config.objects)
        self.env = SharedControlEnv(rendered_context=True, max_episode_steps=config.max_steps + 10,
                                    execution=config.execution, self_contacts=config.self_contacts, **sizes)
        self.speed_limits = controller_speed_limits(self.env.base)
        self.fusion = SharedControlConfig.preset(config.fusion)
        """RT-V3's fusion for the ``rtv3:USER`` drivers (``make_method`` sets its speed limits)."""
        expert_env = gym.make(ENV_ID, obs_mode="state_dict", control_mode="pd_joint_pos_vel",
                              reconfiguration_freq=0, max_episode_steps=10_000, **sizes)
        expert = partial(PandaPlanner, config=with_clearance(config.clearance))
        self.recorder = DemonstrationRecorder(expert_env, expert, plan_timeout=config.plan_timeout)
        self.scene_seed: int | None = None
        self.staging: Any = None
        """The staging area a one-process run writes each rollout and relabel into (None: the run's process writes)."""

    def load_scene(self, scene_seed: int) -> list[int]:
        """Build the scene in both envs; the expert records with the rollout's rendered cloud.
        Returns the feasible goals (:func:`~rtv3_maniskill.benchmarks.goals.check_scene_goals`, the
        benchmark's rule), candidate indices."""
        self.env.reset(seed=scene_seed)
        self.recorder.load_scene(scene_seed)
        cloud, mask = self.env.rendered_point_cloud
        self.recorder.set_scene_point_cloud(cloud[0].cpu().numpy(), mask[0].cpu().numpy())
        self.scene_seed = scene_seed
        checks = check_scene_goals(self.recorder.base, self.recorder.planner, seed=scene_seed)
        return [i for i, check in enumerate(checks) if check == "feasible"]

    def rollout(self, grasp: int, driver: str, seed: int) -> Rollout:
        """One closed-loop rollout of ``driver`` towards grasp ``grasp`` of the loaded scene."""

        method_name, user_name = parse_driver(driver)
        rng = np.random.default_rng(seed)
        if method_name == "prior":  # the planning benchmark's setting: a start drawn around the ready pose
            kin = self.recorder.planner.kin
            q0 = None
            for _ in range(10):
                q = random_start_configuration(rng, kin.lower + 1e-3, kin.upper - 1e-3)
                if self.recorder.planner.is_collision_free(q):
                    q0 = q
                    break
            q0 = READY_QPOS if q0 is None else q0
        else:  # the shared-control benchmark's: the ready pose
            q0 = READY_QPOS
        method = None if method_name == "prior" else make_method(method_name, self.speed_limits, policy=self.policy,
                                                                 config=self.fusion)
        if method is not None:
            self.env.method = method
        obs, info = self.env.reset(seed=self.scene_seed, options=dict(target_grasp_index=grasp, init_qpos=q0))
        if method_name == "prior":
            self.policy.reset()
        user = None if user_name is None else make_user(user_name, seed=int(rng.integers(2**31)))
        if user is not None:
            user.reset(self.env.user_goal())
        states, qpos = [state_vector(obs)], [obs["agent"]["qpos"][0, :7].cpu().numpy()]
        distances = [float(info["pregrasp_distance"][0])]
        outcome = "success" if bool(info["success"][0]) else "timeout"
        steps = 0
        while outcome != "success" and steps < self.config.max_steps:
            if user is None:
                observation = features.observation_from_env(obs)
                observation[features.GRASPS_MASK] = context_mask(observation[features.GRASPS_MASK], grasp, "target")
                twist = self.policy.select_action(observation).reshape(6)
                obs, _, _, _, info = self.env.step_scripted(twist.double(), mode="autonomous")
            else:
                tcp = self.env.base.tcp_pose_matrix[0].detach().cpu().double()
                obs, _, _, _, info = self.env.step(user(tcp))
            steps += 1
            states.append(state_vector(obs))
            qpos.append(obs["agent"]["qpos"][0, :7].cpu().numpy())
            distances.append(float(info["pregrasp_distance"][0]))
            if bool(info["collision"][0]):
                outcome = "collision"
                break
            if bool(info["success"][0]):
                outcome = "success"
        return Rollout(np.stack(states).astype(np.float32), np.stack(qpos).astype(np.float64), outcome, steps,
                       dict(driver=driver, start=q0.tolist()), np.asarray(distances))

    def relabel(self, rollout: Rollout, grasp: int, step: int, seed: int):
        """The expert's demonstration from visited step ``step`` (an ``Episode``), or a failure reason."""
        q = rollout.qpos[step]
        if not self.recorder.planner.is_collision_free(q):
            return "visited_in_collision"
        episode = self.recorder.record_from(q, grasp, seed)
        if isinstance(episode, str):
            return episode
        episode.state[0] = rollout.states[step]  # the visited state, with the rollout's own velocity
        episode.history_prefix = rollout.states[max(0, step - (features.HISTORY_STEPS - 1)) : step].copy()
        episode.info = dict(episode.info, dagger=dict(driver=rollout.info["driver"], step=int(step),
                                                      rollout_outcome=rollout.outcome,
                                                      rollout_steps=int(rollout.steps)))
        return episode

    def close(self) -> None:
        if self.staging is not None:
            self.staging.close()
        self.env.close()
        self.recorder.env.close()


def rollout_variant(driver_index: int, step: int | None = None) -> str:
    """Staging key suffix: ``r{driver}`` for a rollout, ``r{driver}t{step}`` for one of its relabels."""
    return f"r{driver_index}" if step is None else f"r{driver_index}t{step:03d}"


def _init_worker(setting: tuple[DaggerConfig, bool]) -> DaggerCollector:
    """A scene worker's state: the collector with its envs, planner and policy; with ``write_through``
    (a one-process run) also the staging area, written as each rollout and relabel finishes."""
    config, write_through = setting
    torch.set_num_threads(1)
    collector = DaggerCollector(config, load_policy(config.policy_path))
    collector.staging = StagingArea(config.output) if write_through else None
    return collector


def _run_scene(collector: DaggerCollector, job: tuple[int, int, list[str]]) -> dict[str, Any]:
    """Roll out and relabel every not-yet-finished target of one scene; returns what to stage and
    counts for the summary."""
    scene_index, scene_seed, done = job
    config = collector.config
    staged = collector.staging or StagedScene()
    done_keys = set(done)
    start = time.perf_counter()
    counts: Counter = Counter()
    valid = collector.load_scene(scene_seed)
    targets = select_targets(valid, config.targets_per_scene, config.seed, scene_seed, DAGGER_SALT)
    for j, grasp in enumerate(targets):
        d = (scene_index * (config.targets_per_scene or len(targets)) + j) % len(config.drivers)
        if StagingArea.key(scene_seed, grasp, rollout_variant(d)) in done_keys:
            continue
        seed = scene_seed * 1000 + grasp
        rollout = collector.rollout(grasp, config.drivers[d], seed)
        counts[f"rollout_{rollout.outcome}"] += 1
        rng = np.random.default_rng([config.seed, scene_seed, grasp, d])
        for step in relabel_steps(rollout, config.relabels_per_rollout, config.min_step, rng,
                                  config.failure_relabels, config.failure_window):
            variant = rollout_variant(d, step)
            if StagingArea.key(scene_seed, grasp, variant) in done_keys:
                continue
            result = collector.relabel(rollout, grasp, step, seed * 1000 + step)
            if isinstance(result, str):
                staged.log_attempt(scene_seed, grasp, result, variant=variant)
                counts[result] += 1
            else:
                staged.save_success(result, variant=variant)
                counts["success"] += 1
        staged.log_attempt(scene_seed, grasp, f"rollout_{rollout.outcome}", rollout.steps, variant=rollout_variant(d))
    return dict(scene=scene_seed, counts=dict(counts), seconds=time.perf_counter() - start,
                staged=staged if isinstance(staged, StagedScene) else None)


def run_dagger(config: DaggerConfig, progress: bool = True, executor: str = "local",
               ray_address: str | None = None) -> dict[str, Any]:
    """Run (or resume) one DAgger round; exports the LeRobot dataset and returns the summary
    (also written to ``rtv3_summary.json``). Scenes run in ``config.workers`` workers of the scene
    pool (``executor``: local processes or Ray); this process alone writes the staging area, and a
    second process on the same folder stops at once (:class:`~rtv3_maniskill.records.FolderBusy`)."""
    with claim_folder(config.output):
        return _run_claimed(config, progress, executor, ray_address)


def _run_claimed(config: DaggerConfig, progress: bool, executor: str, ray_address: str | None) -> dict[str, Any]:
    policy_config = json.loads((resolve_checkpoint(config.policy_path) / "config.json").read_text())
    num_points, max_grasps = int(policy_config["num_points"]), int(policy_config["max_grasps"])
    with StagingArea(config.output, settings=config.settings(num_points, max_grasps)) as staging:
        attempted = staging.attempts()
    jobs = []
    for i, s in enumerate(scene_seeds(config.seed, config.scenes)):
        prefix = StagingArea.scene_prefix(s)
        jobs.append((i, s, sorted(k for k in attempted if k.startswith(prefix))))
    total: Counter = Counter()
    start = time.perf_counter()
    worker_seconds = 0.0
    bar = tqdm(total=len(jobs), desc="dagger scenes", unit="scene", disable=not progress)
    try:
        with StagingArea(config.output) as staging:
            write_through = config.workers == 1 and executor == "local"
            for result in run_scenes(_init_worker, (config, write_through), _run_scene, jobs, workers=config.workers,
                                     executor=executor, ray_address=ray_address):
                if result["staged"] is not None:
                    staging.write(result["staged"])
                total.update(result["counts"])
                worker_seconds += result["seconds"]
                bar.update(1)
                bar.set_postfix(relabels=total["success"],
                                rollouts=sum(v for k, v in total.items() if k.startswith("roll")))
    finally:
        bar.close()
    with StagingArea(config.output) as staging:
        rows = list(staging.attempts().values())
    frames = export_lerobot_dataset(config.output, num_points, max_grasps, progress=progress)
    outcomes = Counter(r["outcome"] for r in rows)
    summary = dict(
        scenes=len({r["scene"] for r in rows}),
        rollouts={k: v for k, v in outcomes.items() if k.startswith("rollout_")},
        relabelled_trajectories=outcomes.get("success", 0),
        relabel_failures={k: v for k, v in outcomes.items() if k != "success" and not k.startswith("rollout_")},
        frames=frames,
        this_run=dict(total),
        this_run_wall_s=time.perf_counter() - start,
        this_run_worker_s=worker_seconds,
        trajectories_per_core_hour=total["success"] / max(worker_seconds, 1e-9) * 3600,
        config={k: str(v) if isinstance(v, Path) else v for k, v in dataclasses.asdict(config).items()},
    )
    (config.output / "rtv3_summary.json").write_text(json.dumps(summary, indent=2))
    return summary


__all__ = ["DaggerCollector", "Rollout", "relabel_steps", "run_dagger"]
