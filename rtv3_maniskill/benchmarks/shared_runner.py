"""Running the shared-control benchmark (paper Sec. "Simulated Shared Control Experiments", Table II).

The authors' protocol (docs/PAPER_DETAILS.md, "Authors' benchmark protocol"): the goals are the
*feasible* grasp candidates of each scene (:mod:`rtv3_maniskill.benchmarks.goals`: collision-free
IK at the pre-grasp and a free straight 5 cm approach; the others are counted by reason in
``goals.csv`` and never run), optionally a seeded random subset of ``goals_per_scene`` per scene;
every trial starts from the Panda ready pose, and each simulated user drives towards the goal's
pre-grasp with each assistance method (:data:`~rtv3_maniskill.shared_control.methods.METHODS`) for
up to 150 steps (7.5 s). As in the paper's planning and shared-control tables (their SR + CR + TOR
add up to 100 %), each trial has one outcome: it ends as a *collision* at the first robot contact,
as a *success* when the env's ``info["success"]`` comes first (pose distance to the pre-grasp < 0.1,
shared-control weights, either parallel-jaw twin), and as a *timeout* after the step limit.

Methods that know the scene (the oracles, RT-V3 told the target) are told each trial's goals
before it starts (:attr:`~rtv3_maniskill.shared_control.methods.MethodSpec.prepare`).

Scene ``i`` uses seed ``seed * 100000 + i`` (``rtv3 generate``'s convention; the default seed 9
keeps the benchmark scenes apart from training scenes made with seeds 0..8). The user's random
stream depends only on (seed, scene, grasp, user), so every method faces the same noise. Outputs
in ``config.output``: the run's files (:mod:`~rtv3_maniskill.benchmarks.shared_results`) and its
report (:mod:`~rtv3_maniskill.benchmarks.shared_report`).
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from rtv3_maniskill.benchmarks.episodes import SharedControlEnv, controller_speed_limits, run_episode
from rtv3_maniskill.benchmarks.goals import check_scene_goals
from rtv3_maniskill.benchmarks.plan_oracle import PlanOraclePrior
from rtv3_maniskill.benchmarks.shared_config import BenchmarkConfig, BenchmarkError
from rtv3_maniskill.benchmarks.shared_report import method_label, write_summaries
from rtv3_maniskill.benchmarks.shared_results import goals_store, results_store
from rtv3_maniskill.features import pregrasp_poses
from rtv3_maniskill.records import claim_folder, select_targets
from rtv3_maniskill.robot.planner import PandaPlanner
from rtv3_maniskill.robot.scene_geometry import READY_QPOS
from rtv3_maniskill.scene_pool import EXECUTORS, run_scenes
from rtv3_maniskill.shared_control.methods import METHODS, Trial, make_method
from rtv3_maniskill.shared_control.simulated_users import make_user

TARGET_SALT = 17
"""Salt of the seeded goal choice (:func:`rtv3_maniskill.records.select_targets`) of benchmark runs."""


def user_seed(seed: int, scene_seed: int, grasp_index: int, user: str) -> int:
    """Seed of the user's noise in one trial: same for every method."""
    return int(np.random.SeedSequence([seed, scene_seed, grasp_index, zlib.crc32(user.encode())]).generate_state(1)[0])


def trial_options(grasp_index: int) -> dict[str, Any]:
    """Reset options of one trial: its target, and the arm at the Panda ready pose."""
    return dict(target_grasp_index=int(grasp_index), init_qpos=READY_QPOS)


def _policy_path(config: BenchmarkConfig) -> Path:
    """The checkpoint's local folder (a Hub repo id resolved to its cached snapshot)."""
    # Lazy: the policy package loads LeRobot's config (~1.5 s); only runs of the learned methods need it.
    from rtv3_maniskill.policies.rtv3.checkpoints import resolve_checkpoint

    return resolve_checkpoint(config.policy_path)


class SceneRunner:
    """One process's env and assistance methods: runs the trials of one scene at a time (the whole
    run in a serial run, one worker's share with ``workers > 1``)."""

    def __init__(self, config: BenchmarkConfig, policy: Any = None) -> None:
        torch.set_num_threads(1)
        self.config = config
        if config.needs_policy and policy is None:
            from rtv3_maniskill.policies.rtv3.checkpoints import load_policy  # lazy: see _policy_path

            policy = load_policy(_policy_path(config))  # clear error when missing
        env_kwargs = config.env_kwargs()
        if policy is not None:
            env_kwargs.update(num_points=int(policy.config.num_points), max_grasps=int(policy.config.max_grasps))
        self.env = SharedControlEnv(rendered_context=True, safety_filter=config.safety_filter,
                                    **env_kwargs)
        self.suffix = f"+{config.safety_filter}" if config.safety_filter else ""
        limits = controller_speed_limits(self.env.base)
        shared_config = config.shared_control_config(*limits)
        self.specs = {m: METHODS[m] for m in config.methods}
        copilot = config.copilot_settings() if "copilot" in config.methods else None
        self.methods = {m: make_method(m, limits, policy=policy, config=shared_config, plan_prior=PlanOraclePrior,
                                       copilot=copilot)
                        for m in config.methods}

    def run_scene(self, scene_seed: int, checks: dict[int, str], done: set[tuple[str, ...]],
                  on_checks: Callable[[list[dict[str, Any]]], None] | None = None,
                  on_plan: Callable[[int], None] | None = None,
                  on_trial: Callable[[dict[str, Any]], None] | None = None) -> tuple[list[dict], list[dict]]:
        """Every trial of scene ``scene_seed`` not in ``done`` (result keys, as ``results.csv`` holds
        them: strings).

        ``checks`` maps the grasp indices already checked to their verdict (``goals.csv``); the
        scene's missing checks are made here; ``on_checks(rows)`` hears them before any trial runs,
        ``on_plan(n)`` the scene's number of trials, ``on_trial(row)`` each result as it finishes.
        Returns the new goal-check rows and the result rows.
        """
        config, env = self.config, self.env
        env.reset(seed=scene_seed)
        count = int((env.base.grasps_mask[0] > 0.5).sum())
        new_checks: list[dict[str, Any]] = []
        unchecked = any(i not in checks for i in range(count))  # a scene not checked yet (or only in part)
        planner = None
        if unchecked or config.needs_planner:
            planner = PandaPlanner(env.base.layouts[0])
        if unchecked:
            checks = dict(checks)
            for i, check in enumerate(check_scene_goals(env.base, planner, seed=scene_seed)):
                if i not in checks:
                    checks[i] = check
                    new_checks.append(dict(scene_seed=scene_seed, grasp_index=i, check=check))
        if on_checks is not None:
            on_checks(new_checks)
        feasible = [i for i in range(count) if config.goals == "all" or checks[i] == "feasible"]
        grasps = select_targets(feasible, config.goals_per_scene, config.seed, scene_seed, salt=TARGET_SALT)
        pregrasps = pregrasp_poses(env.base.grasp_poses[0].double())
        if on_plan is not None:
            on_plan(len(grasps) * len(config.users) * len(config.methods))
        rows: list[dict[str, Any]] = []
        for g in grasps:
            trial = Trial(target=g, pregrasps=pregrasps, goals=tuple(feasible), grasp_pose=env.base.grasp_poses[0, g],
                          planner=planner if config.needs_planner else None)
            for user_name in config.users:
                u_seed = user_seed(config.seed, scene_seed, g, user_name)
                for method_name, method in self.methods.items():
                    if (str(scene_seed), str(g), user_name, method_name + self.suffix) in done:
                        continue
                    start = time.perf_counter()
                    prepare = self.specs[method_name].prepare
                    if prepare is not None:
                        prepare(method, trial)
                    result = run_episode(env, method, make_user(user_name, u_seed), max_steps=config.max_steps,
                                         seed=scene_seed, options=trial_options(g),
                                         stop_on_contact=True)
                    counts = result.mode_counts
                    row = dict(
                        scene_seed=scene_seed, grasp_index=g, user=user_name, method=method_name + self.suffix,
                        outcome=result.outcome, success=int(result.success), collision=int(result.collision),
                        steps=result.steps,
                        final_distance=f"{result.final_distance:.4f}",
                        autonomous_steps=counts.get("autonomous", 0), user_only_steps=counts.get("user_only", 0),
                        user_seed=u_seed, wall_time_s=f"{time.perf_counter() - start:.2f}",
                        qp_infeasible_steps=result.qp_infeasible_steps, contact=result.contact,
                        twist_deviation=f"{result.twist_deviation:.4f}",
                    )
                    rows.append(row)
                    if on_trial is not None:
                        on_trial(row)
        return new_checks, rows

    def close(self) -> None:
        self.env.close()


def _run_scene_job(runner: SceneRunner, job: tuple[int, dict[int, str], set[tuple[str, ...]]]
                   ) -> tuple[list[dict], list[dict]]:
    return runner.run_scene(*job)


def run_benchmark(config: BenchmarkConfig, policy: Any = None, progress: bool = True,
                  workers: int = 1, executor: str = "local", ray_address: str | None = None) -> list[dict[str, Any]]:
    """Run (or resume) the benchmark; returns the summary rows. ``policy`` overrides ``policy_path``.

    ``workers > 1`` or ``executor="ray"`` runs scenes in that many workers of the scene pool
    (:func:`rtv3_maniskill.scene_pool.run_scenes`; each loads the policy from ``policy_path``, so
    ``policy`` must be None); this process alone writes ``results.csv`` and ``goals.csv``, a scene's
    rows once the scene is done, so an interrupted run loses at most the scenes in flight and the
    folder is the same as a serial run's (either resumes the other). A failing worker stops the run
    (:class:`~rtv3_maniskill.scene_pool.SceneWorkerError`). An output folder holding results of other
    settings, or files with other columns, is refused (:class:`BenchmarkError`).
    """
    if workers < 1:
        raise BenchmarkError(f"workers must be >= 1, got {workers}")
    if executor not in EXECUTORS:
        raise BenchmarkError(f"unknown executor {executor!r}; known: {', '.join(EXECUTORS)}")
    serial = workers == 1 and executor == "local"
    if not serial and policy is not None:
        raise BenchmarkError("a policy object cannot be sent to worker processes: give policy_path with workers > 1")
    output = config.output
    if output.exists() and not output.is_dir():
        raise BenchmarkError(f"--output {output} is a file, not a folder; give a folder for the results")
    with claim_folder(output):  # one writer per folder: a second run stops here (FolderBusy names the first)
        return _run_claimed(config, policy, progress, workers, executor, ray_address)


def _run_claimed(config: BenchmarkConfig, policy: Any, progress: bool, workers: int, executor: str,
                 ray_address: str | None) -> list[dict[str, Any]]:
    serial = workers == 1 and executor == "local"
    output = config.output
    policy_path = None
    if config.needs_policy and (policy is None or config.policy_path is not None):
        policy_path = _policy_path(config)
    fingerprint = config.fingerprint(policy_path)
    results = results_store(output, fingerprint)
    try:
        goal_checks = goals_store(output, fingerprint)
    except BenchmarkError:
        results.close()
        raise
    done_by_scene: dict[int, set[tuple[str, ...]]] = {}
    for row in results.rows:
        done_by_scene.setdefault(int(row["scene_seed"]), set()).add(results.key(row))
    checked: dict[int, dict[int, str]] = {}
    for row in goal_checks.rows:
        checked.setdefault(int(row["scene_seed"]), {})[int(row["grasp_index"])] = row["check"]
    jobs = [(s, checked.get(s, {}), done_by_scene.get(s, set())) for s in config.scene_seeds()]

    # One process: a bar over trials (their number known scene by scene); several: over scenes.
    bar = tqdm(total=0 if serial else len(jobs), unit="trial" if serial else "scene",
               disable=not progress, dynamic_ncols=True)
    wins: dict[str, list[int]] = {}

    def plan(trials: int) -> None:
        bar.total += trials
        bar.refresh()

    def record(row: dict[str, Any]) -> None:
        results.append(row)
        wins.setdefault(row["method"], []).append(int(row["outcome"] == "success"))
        bar.set_postfix({method_label(m): f"{100 * np.mean(v):.0f}%" for m, v in wins.items()})

    def record_trial(row: dict[str, Any]) -> None:
        record(row)
        bar.update(1)

    def record_checks(rows: list[dict[str, Any]]) -> None:
        for row in rows:
            goal_checks.append(row)

    runner = None
    try:
        if serial:
            runner = SceneRunner(config, policy)
            for scene_seed, checks, done in jobs:
                runner.run_scene(scene_seed, checks, done, on_checks=record_checks, on_plan=plan, on_trial=record_trial)
                bar.update(len(done))  # the scene's trials finished in an earlier run
        else:
            for new_checks, rows in run_scenes(SceneRunner, config, _run_scene_job, jobs, workers=workers,
                                               executor=executor, ray_address=ray_address):
                record_checks(new_checks)
                for row in rows:
                    record(row)
                bar.update(1)
    finally:
        if runner is not None:
            runner.close()
        bar.close()
        results.close()
        goal_checks.close()
    return write_summaries(output, config.users, config.methods)
