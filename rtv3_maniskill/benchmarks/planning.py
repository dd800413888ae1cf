"""Closed-loop planning benchmark of the RT-V3 prior (paper Sec. VI-B "Planning in the Simulation
Environment", Table I right half; docs/PAPER_DETAILS.md "Metrics").

Protocol:

* scenes: ``GraspClutter-v1`` (``obs_mode="state_dict"``, ``control_mode="pd_ee_twist"``), scene
  ``i`` has seed ``seed * 100000 + i`` (``rtv3 generate``'s numbering: pick a ``seed`` that no
  training data used; the default 9 matches ``rtv3 benchmark-shared``);
* targets: ``max_grasps_per_scene`` grasp candidates per scene (a seeded random subset; the
  paper selects two per scene), one trial per (scene, grasp);
* start: a collision-free draw of the demonstrations' start distribution (the ready pose plus
  per-joint Gaussian noise, ``random_start_configuration``), the robot reset there (``init_qpos``);
* context: the paper selects target grasps and counts reaching "one of the target poses" as
  a success, i.e. the target poses are the grasp context the policy sees. ``context="target"``
  (default) shows the policy only the trial's target grasp (all other rows of
  ``observation.grasps_mask`` set to 0); ``context="all"`` shows every candidate and counts
  reaching any of them (a reactive-planning test without intent);
* control: every 50 ms step the policy's most likely action (ML setting: argmax z, then the
  mode of each Gaussian) from ``select_action``; ``policy.reset()`` per trial;
* outcome per trial (exclusive, so SR + CR + TOR = 1): ``collision`` at the first step with
  any robot contact (the env's ``info["collision"]``; the ``contact`` column says with what:
  ``table``, ``object`` or ``self``), else ``success`` at the first step whose
  planning distance to a context grasp's pre-grasp, or its pi-about-z twin, is below 0.2
  (the paper's pose distance with rotation weight 0.3/pi, docs/PAPER_DETAILS.md "Metrics"), else
  ``timeout`` after 150 steps (7.5 s). Trials without a collision-free start pose are logged
  as ``no_start_pose`` and left out of the rates.
* arm reach: each target is also checked as ``rtv3 benchmark-shared`` checks goals
  (:func:`~rtv3_maniskill.benchmarks.goals.check_goal`: a collision-free IK solution at the pre-grasp,
  then a straight 5 cm approach); every target is run, and the summary adds the rates on the targets
  that pass (``arm_reachable``), the set the authors' targets came from (their planner's demonstrations).

The success rule is :mod:`~rtv3_maniskill.benchmarks.planning_success`, the records
:mod:`~rtv3_maniskill.benchmarks.planning_records`, the NeoSS command
:mod:`~rtv3_maniskill.benchmarks.straight_to_pregrasp`.

Outputs in ``output``: ``planning_trials.csv`` (one row per trial, appended and flushed as it
finishes; a rerun skips finished (scene, grasp) rows), ``planning_summary.json`` and
``planning_config.json`` (a resumed run must use the same settings).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

from rtv3_maniskill import ENV_ID, features
from rtv3_maniskill.benchmarks.goals import check_candidate
from rtv3_maniskill.benchmarks.outcomes import describe_contact, trial_outcome
from rtv3_maniskill.benchmarks.planning_records import (
    NO_START_POSE,
    by_goal_check,
    check_baseline,
    goals_store,
    paired_with_baseline,
    scene_index,
    summarize,
    trials_store,
)
from rtv3_maniskill.benchmarks.planning_success import (
    PLANNING_SUCCESS_THRESHOLD,
    is_planning_success,
    planning_distance,
)
from rtv3_maniskill.benchmarks.straight_to_pregrasp import StraightToPregrasp
from rtv3_maniskill.features import CONTEXT_MODES, GRIPPER_OPEN, context_mask
from rtv3_maniskill.policies.rtv3.checkpoints import load_policy, resolve_checkpoint
from rtv3_maniskill.records import SCENE_SEED_STRIDE, claim_folder, scene_seeds, select_targets
from rtv3_maniskill.robot.neo_qp import NeoSafetyFilter
from rtv3_maniskill.robot.planner import PandaPlanner
from rtv3_maniskill.robot.starts import random_start_configuration

PLANNING_MAX_STEPS = 150
"""7.5 s at 20 Hz."""
TARGET_SALT = 29
"""Salt of the seeded target choice (:func:`rtv3_maniskill.records.select_targets`) of planning runs."""
MAX_GRASPS_GUESS = 16
"""Progress-bar estimate of the targets per scene when every grasp is a target."""
PLANNERS = ("policy", "neoss")
POINT_CLOUD_SOURCES = ("rendered", "mesh")
PAPER_TABLE1_FULL = {"SR": 0.904, "CR": 0.079, "TOR": 0.017}


# ----------------------------------------------------------------------------- settings


@dataclass
class PlanningConfig:
    """Settings of one ``rtv3 evaluate planning`` run."""

    output: Path
    policy_path: Path | None = None
    scenes: int = 20
    seed: int = 9
    max_grasps_per_scene: int | None = 2
    context: str = "target"
    point_cloud: str = "rendered"
    """``"rendered"``: the depth camera's cloud captured once per scene (``rtv3 generate``'s default);
    ``"mesh"``: sampled from the object meshes (``rtv3 generate --context mesh``).
    Use what the policy was trained on."""
    scene_type: str = "mixed"
    object_source: str = "procedural"
    execution: str = "capped"
    """How the env executes the prior's twist (``rtv3_maniskill.presets.EXECUTIONS``)."""
    self_contacts: bool = True
    """Whether a robot self contact counts as a collision."""
    max_steps: int = PLANNING_MAX_STEPS
    threshold: float = PLANNING_SUCCESS_THRESHOLD
    start_pose_attempts: int = 10
    planner: str = "policy"
    """``"policy"``: the RT-V3 prior's most likely actions; ``"neoss"``: the paper's reactive
    baseline, a straight twist to the target's pre-grasp through the NEO collision damper
    (``pd_ee_twist_qp`` + ``NeoSafetyFilter``), Table I's NeoSS row."""

    def __post_init__(self) -> None:
        self.output = Path(self.output).expanduser()
        if self.planner not in PLANNERS:
            raise ValueError(f"unknown planner {self.planner!r}; expected one of {PLANNERS}")
        if self.scenes < 1:
            raise ValueError(f"scenes must be >= 1, got {self.scenes}")
        if self.max_grasps_per_scene is not None and self.max_grasps_per_scene < 1:
            raise ValueError(f"max_grasps_per_scene must be >= 1 (or None for all), got {self.max_grasps_per_scene}")
        if self.context not in CONTEXT_MODES:
            raise ValueError(f"unknown context mode {self.context!r}; expected one of {CONTEXT_MODES}")
        if self.point_cloud not in POINT_CLOUD_SOURCES:
            raise ValueError(f"unknown point-cloud source {self.point_cloud!r}; expected one of {POINT_CLOUD_SOURCES}")
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        if not (self.threshold > 0 and math.isfinite(self.threshold)):
            raise ValueError(f"threshold must be a positive number, got {self.threshold}")
        if self.start_pose_attempts < 1:
            raise ValueError(f"start_pose_attempts must be >= 1, got {self.start_pose_attempts}")

    def fingerprint(self) -> dict[str, Any]:
        """Settings that change a trial's outcome: a resumed run must match them."""
        return dict(
            seed=self.seed, context=self.context, point_cloud=self.point_cloud, scene_type=self.scene_type,
            max_steps=self.max_steps, threshold=self.threshold, start_pose_attempts=self.start_pose_attempts,
            policy_path=str(resolve_checkpoint(self.policy_path).resolve()) if self.policy_path is not None else None,
            planner=self.planner,
            # Only when set, so that runs made before these options existed still resume.
            **({"object_source": self.object_source} if self.object_source != "procedural" else {}),
            **({"execution": self.execution} if self.execution != "capped" else {}),
            **({"self_contacts": self.self_contacts} if not self.self_contacts else {}),
        )


# ----------------------------------------------------------------------------- running


class PlanningBenchmark:
    """One ``GraspClutter-v1`` env, the planner for start poses, and the policy under test."""

    def __init__(self, config: PlanningConfig, policy: Any) -> None:
        self.config = config
        self.policy = policy
        self._env = None
        self.scene_seed: int | None = None
        self.planner = None
        self._cloud: tuple[torch.Tensor, torch.Tensor] | None = None
        self.safety_filter = None
        if config.planner == "neoss":
            self.safety_filter = NeoSafetyFilter()

    @property
    def env(self):
        """The env, made on first use (a fully resumed run never builds it)."""
        if self._env is None:
            self._env = self._make_env()
        return self._env

    @property
    def base(self):
        return self.env.unwrapped

    def _make_env(self):
        config, policy = self.config, self.policy
        return gym.make(
            ENV_ID,
            obs_mode="state_dict",
            control_mode="pd_ee_twist_qp" if config.planner == "neoss" else "pd_ee_twist",
            scene_type=config.scene_type,
            object_source=config.object_source,
            execution=config.execution,
            self_contacts=config.self_contacts,
            num_points=int(policy.config.num_points),
            max_grasps=int(policy.config.max_grasps),
            reconfiguration_freq=0,
            max_episode_steps=config.max_steps + 10,  # the benchmark stops trials itself
        )

    def load_scene(self, scene_seed: int) -> list[int]:
        """Build the scene of ``scene_seed`` (reconfigure); returns its valid grasp indices."""
        self.env.reset(seed=scene_seed, options=dict(reconfigure=True))
        self.scene_seed = scene_seed
        self.planner = PandaPlanner(self.base.layouts[0])
        self._cloud = None
        if self.config.point_cloud == "rendered":
            if not self.base.scene.can_render():
                raise ValueError(
                    "--point-cloud rendered: the scene cannot render, so there is no depth-camera point cloud; "
                    "use --point-cloud mesh "
                    "(only if the policy was trained on mesh clouds) or set up a Vulkan driver "
                    "(scripts/setup.sh installs a software one)"
                )
            self._cloud = self.base.capture_point_cloud()
        return torch.nonzero(self.base.grasps_mask[0] > 0.5).flatten().tolist()

    def _observation(self, obs: dict, target: int) -> dict[str, torch.Tensor]:
        observation = features.observation_from_env(obs)
        if self._cloud is not None:
            observation[features.POINT_CLOUD] = self._cloud[0].float()
            observation[features.POINT_CLOUD_MASK] = self._cloud[1].float()
        observation[features.GRASPS_MASK] = context_mask(observation[features.GRASPS_MASK], target, self.config.context)
        return observation

    def goal_check(self, grasp: int) -> str:
        """The arm-reach check of grasp ``grasp`` of the loaded scene (``benchmarks.goals.GOAL_CHECKS``), seeded
        as ``rtv3 benchmark-shared`` seeds it."""
        return check_candidate(self.base, self.planner, grasp, seed=int(self.scene_seed))

    def start_configuration(self, grasp: int, context_poses: torch.Tensor) -> tuple[np.ndarray | None, int]:
        """Collision-free start joints for the trial and the attempts it took (None if none was found).

        Start poses already within the success threshold of a context grasp are redrawn.
        """
        rng = np.random.default_rng([self.config.seed, int(self.scene_seed), grasp])
        kin = self.planner.kin
        for attempt in range(1, self.config.start_pose_attempts + 1):
            q = random_start_configuration(rng, kin.lower + 1e-3, kin.upper - 1e-3)
            pose = torch.as_tensor(kin.forward_kinematics(q))
            if bool(is_planning_success(planning_distance(pose, context_poses).min(), self.config.threshold)):
                continue
            if self.planner.is_collision_free(q):
                return q, attempt
        return None, self.config.start_pose_attempts

    def run_trial(self, grasp: int) -> dict[str, Any]:
        """One trial towards grasp ``grasp`` of the loaded scene; a ``planning_trials.csv`` row."""
        start_time = time.perf_counter()
        valid = self.base.grasps_mask[0] > 0.5
        context = torch.zeros_like(valid)
        if self.config.context == "target":
            context[grasp] = True
        else:
            context = valid.clone()
        context_indices = torch.nonzero(context).flatten()
        context_poses = self.base.grasp_poses[0, context_indices].double()
        row: dict[str, Any] = dict(
            scene_seed=int(self.scene_seed), grasp_index=grasp, context_grasps=int(len(context_indices)),
            reached_grasp=-1, start_distance="", final_distance="", min_distance="", contact="",
        )
        q_start, attempts = self.start_configuration(grasp, context_poses)
        row["start_attempts"] = attempts
        if q_start is None:
            row.update(outcome=NO_START_POSE, steps=0, wall_time_s=f"{time.perf_counter() - start_time:.2f}")
            return row
        obs, _ = self.env.reset(options=dict(reconfigure=False, init_qpos=q_start, target_grasp_index=grasp))
        if self.config.planner == "neoss":  # a reset rebuilds the controllers: attach the damper again
            # Imported here: the twist controller module loads ManiSkill, which only a neoss run needs.
            from rtv3_maniskill.robot.twist_controller import attach_safety_filters, target_object_index

            self.safety_filter.reset(self.base.layouts[0], target_object=target_object_index(self.env))
            attach_safety_filters(self.env, [self.safety_filter])
        self.policy.reset()
        row["start_distance"] = (
            f"{float(planning_distance(self.base.tcp_pose_matrix[0].double(), context_poses).min()):.4f}"
        )
        outcome, steps, min_distance, distances = "timeout", self.config.max_steps, math.inf, None
        for step in range(1, self.config.max_steps + 1):
            twist = self.policy.select_action(self._observation(obs, grasp))
            command = torch.cat([twist.reshape(1, 6).float().cpu(), torch.tensor([[GRIPPER_OPEN]])], -1)
            obs, _, _, _, info = self.env.step(command)
            tcp = self.base.tcp_pose_matrix[0].double()
            distances = planning_distance(tcp, context_poses)
            min_distance = min(min_distance, float(distances.min()))
            reached = bool(is_planning_success(distances.min(), self.config.threshold))
            decided = trial_outcome(collision=bool(info["collision"][0]), success=reached)
            if decided is not None:
                outcome, steps = decided, step
                if decided == "collision":
                    row["contact"] = describe_contact(self.base)
                if decided == "success":
                    row["reached_grasp"] = int(context_indices[int(distances.argmin())])
                break
        row.update(
            outcome=outcome, steps=steps, final_distance=f"{float(distances.min()):.4f}",
            min_distance=f"{min_distance:.4f}", wall_time_s=f"{time.perf_counter() - start_time:.2f}",
        )
        return row

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None


def run_planning_benchmark(config: PlanningConfig, policy: Any = None, progress: bool = True,
                           baseline: Path | None = None) -> dict[str, Any]:
    """Run (or resume) the benchmark; returns the summary (also written to ``planning_summary.json``).

    ``policy`` overrides loading ``config.policy_path``; ``baseline``: a finished run's folder to pair this
    run with, trial for trial (the summary's ``paired_with``, :func:`planning_records.paired_with_baseline`).
    """
    settings = config.fingerprint()
    if baseline is not None:
        check_baseline(baseline, settings)  # a missing or mismatched one fails before any trial
    with claim_folder(config.output):  # one writer per folder: a second run stops here (FolderBusy names the first)
        return _run_claimed(config, policy, progress, baseline, settings)


def _run_claimed(config: PlanningConfig, policy: Any, progress: bool, baseline: Path | None,
                 settings: dict[str, Any]) -> dict[str, Any]:
    torch.set_num_threads(1)
    if policy is None and config.planner == "neoss":
        policy = StraightToPregrasp()
    if policy is None:
        if config.policy_path is None:
            raise ValueError("no policy: pass --policy.path (an RT-V3 checkpoint folder)")
        policy = load_policy(config.policy_path)
    output = config.output
    output.mkdir(parents=True, exist_ok=True)
    trials = trials_store(output, settings)
    scenes = scene_index(output, settings)
    goals = goals_store(output, settings)
    bench = PlanningBenchmark(config, policy)
    keys: list[tuple[int, int]] = []
    per_scene = config.max_grasps_per_scene or MAX_GRASPS_GUESS
    bar = tqdm(total=config.scenes * per_scene, unit="trial", desc="planning", disable=not progress, dynamic_ncols=True)
    try:
        for scene_seed in scene_seeds(config.seed, config.scenes):
            known = scenes.get((scene_seed,))
            if known is None:
                valid = bench.load_scene(scene_seed)
                scenes.append(dict(scene_seed=scene_seed, valid_grasps=" ".join(str(g) for g in valid)))
            else:
                valid = [int(g) for g in known["valid_grasps"].split()]
            targets = select_targets(valid, config.max_grasps_per_scene, config.seed, scene_seed, salt=TARGET_SALT)
            bar.total += len(targets) - per_scene  # the estimate made before the scene was known
            bar.refresh()
            for g in targets:
                key = (scene_seed, g)
                keys.append(key)
                if (key not in goals or key not in trials) and bench.scene_seed != scene_seed:
                    bench.load_scene(scene_seed)
                if key not in goals:
                    goals.append(dict(scene_seed=scene_seed, grasp_index=g, check=bench.goal_check(g)))
                if key not in trials:
                    trials.append(bench.run_trial(g))
                bar.update(1)
                stats = summarize(trials.get(k) for k in keys)
                if stats["trials"]:  # rates exist
                    bar.set_postfix({k: f"{100 * stats[k]:.0f}%" for k in ("SR", "CR", "TOR")})
    finally:
        bar.close()
        trials.close()
        scenes.close()
        goals.close()
        bench.close()
    summary = summarize(trials.get(k) for k in keys)
    goal_of = {k: goals.get(k)["check"] for k in keys}
    summary.update(by_goal_check((trials.get(k) for k in keys), goal_of))
    summary.update(
        scenes=config.scenes,
        scene_seed_range=[config.seed * SCENE_SEED_STRIDE, config.seed * SCENE_SEED_STRIDE + config.scenes - 1],
        max_grasps_per_scene=config.max_grasps_per_scene,
        settings=settings,
        success_rule=("pose distance (rot weight 0.3/pi) to a context grasp's pre-grasp "
                      f"or its twin < {config.threshold}"),
        paper_table1_full_rtv3=PAPER_TABLE1_FULL,
    )
    if baseline is not None:
        summary["paired_with"] = paired_with_baseline((trials.get(k) for k in keys), baseline)
    (output / "planning_summary.json").write_text(json.dumps(summary, indent=2))
    return summary
