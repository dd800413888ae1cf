"""``rtv3 generate``: expert demonstrations from the motion planner -> LeRobot v3 dataset.

Resumable: run the same command again after an interruption and it continues where it
stopped (finished episodes are kept, attempted grasps are not retried).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from rtv3_maniskill.cli.scene_args import (
    add_clearance_argument,
    add_executor_arguments,
    add_push_argument,
    add_scene_arguments,
    check_push_argument,
    push_if_asked,
    resolve_scene_arguments,
)
from rtv3_maniskill.records import claim_folder, scene_seeds
from rtv3_maniskill.robot.planner_config import DEFAULT_CLEARANCE, with_clearance


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--num-scenes", type=int, required=True, help="clutter scenes to draw")
    parser.add_argument("--output", type=Path, required=True, help="dataset folder (LeRobot root)")
    parser.add_argument("--seed", type=int, default=0, help="scene i uses seed SEED*100000 + i")
    parser.add_argument("--workers", type=int, default=1, help="parallel CPU workers (processes or Ray actors)")
    add_executor_arguments(parser)
    add_push_argument(parser)
    add_scene_arguments(parser, execution=False)
    parser.add_argument("--grasps-per-scene", type=int, default=None, help="cap on targets per scene (default all)")
    parser.add_argument("--num-points", type=int, default=512,
                        help="points per stored cloud (rendered workspace clouds at 7.5 mm hold ~150-450)")
    parser.add_argument("--max-grasps", type=int, default=64)
    parser.add_argument("--context", default="rendered", choices=["rendered", "mesh"],
                        help="scene point cloud from the depth camera (rendered once per scene) or mesh samples")
    parser.add_argument("--plan-timeout", type=float, default=3.0, help="seconds per OMPL query")
    add_clearance_argument(parser)
    parser.add_argument("--end-at", default="pregrasp", choices=["pregrasp", "grasp"],
                        help="demonstrations end at the pre-grasp (paper) "
                             "or go on along the 5 cm approach to the grasp")
    parser.add_argument("--export-only", action="store_true",
                        help="only (re)build the LeRobot dataset from the episodes finished so far")


def _validate(args: argparse.Namespace) -> None:
    for name in ("num_scenes", "workers", "num_points", "max_grasps"):
        if getattr(args, name) <= 0:
            raise SystemExit(f"error: --{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.grasps_per_scene is not None and args.grasps_per_scene <= 0:
        raise SystemExit(f"error: --grasps-per-scene must be positive, got {args.grasps_per_scene}")
    parent = args.output.expanduser().absolute().parent
    if not parent.is_dir():
        raise SystemExit(f"error: the parent folder of --output does not exist: {parent}")
    from rtv3_maniskill.tasks.object_library import make_object_set

    try:  # before anything is written: a failed run must not leave a folder that blocks the rerun
        make_object_set(args.objects)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"error: --objects: {err}") from None
    try:
        with_clearance(args.clearance)
    except ValueError as err:
        raise SystemExit(f"error: --clearance: {err}") from None


def _settings(args: argparse.Namespace) -> dict:
    return dict(
        format="rtv3-grasp-clutter-v1",
        seed=args.seed,
        scene_type=args.scene_type,
        objects=args.objects,
        num_points=args.num_points,
        max_grasps=args.max_grasps,
        context=args.context,
        end_at=args.end_at,
        # Only when set, so that datasets made before the option existed still resume.
        **({"clearance": args.clearance} if args.clearance != DEFAULT_CLEARANCE else {}),
    )


@dataclass
class _Worker:
    """A scene worker's state: the planner's demonstration recorder (with its env), the run's
    settings, and for a one-process run the staging area it writes into."""

    recorder: Any
    args: dict
    staging: Any = None

    def close(self) -> None:
        if self.staging is not None:
            self.staging.close()
        self.recorder.env.close()


def _init_worker(args_dict: dict) -> _Worker:
    """A scene worker's state: its env and the planner's demonstration recorder."""
    import gymnasium as gym
    import torch

    import rtv3_maniskill  # noqa: F401
    from rtv3_maniskill.datagen.demonstrations import DemonstrationRecorder
    from rtv3_maniskill.datagen.lerobot_export import StagingArea
    from rtv3_maniskill.robot.planner import PandaPlanner

    torch.set_num_threads(1)
    env = gym.make(
        "GraspClutter-v1",
        obs_mode="state_dict",
        control_mode="pd_joint_pos_vel",
        scene_type=args_dict["scene_type"],
        object_source=args_dict["objects"],
        num_points=args_dict["num_points"],
        max_grasps=args_dict["max_grasps"],
        reconfiguration_freq=0,
        max_episode_steps=10_000,
    )
    recorder = DemonstrationRecorder(env, partial(PandaPlanner, config=with_clearance(args_dict["clearance"])),
                                     plan_timeout=args_dict["plan_timeout"], end_at=args_dict["end_at"])
    # A one-process run writes each target into the staging area as it finishes (nothing to send back).
    staging = StagingArea(Path(args_dict["output"])) if args_dict["write_through"] else None
    return _Worker(recorder, args_dict, staging)


def _run_scene(worker: _Worker, job: tuple[int, list[str]]) -> dict:
    """Record every not-yet-attempted grasp of one scene; returns what to stage and counts for the summary."""
    from rtv3_maniskill.datagen.lerobot_export import StagedScene, StagingArea

    scene_seed, done_keys = job
    args = worker.args
    recorder = worker.recorder
    staged = worker.staging or StagedScene()
    start = time.perf_counter()
    num_grasps = recorder.load_scene(scene_seed)
    if args["context"] == "rendered" and recorder.base.scene.can_render():
        cloud, mask = recorder.base.capture_point_cloud()
        recorder.set_scene_point_cloud(cloud[0].cpu().numpy(), mask[0].cpu().numpy())
    grasps = range(num_grasps if args["grasps_per_scene"] is None else min(num_grasps, args["grasps_per_scene"]))
    outcomes: Counter = Counter()
    frames = 0
    for g in grasps:
        key = StagingArea.key(scene_seed, g)
        if key in done_keys:
            continue
        result = recorder.record(g, seed=scene_seed * 1000 + g)
        if isinstance(result, str):
            staged.log_attempt(scene_seed, g, result)
            outcomes[result] += 1
        else:
            staged.save_success(result)
            outcomes["success"] += 1
            frames += len(result.state)
    return dict(scene=scene_seed, grasps=len(grasps), outcomes=dict(outcomes), frames=frames,
                seconds=time.perf_counter() - start, staged=staged if isinstance(staged, StagedScene) else None)


def run(args: argparse.Namespace) -> int:
    resolve_scene_arguments(args)
    _validate(args)
    check_push_argument(args)
    args.output = args.output.expanduser().absolute()
    with claim_folder(args.output):  # one writer per folder: a second run stops here (FolderBusy names the first)
        return _generate(args)


def _generate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from rtv3_maniskill.datagen.lerobot_export import StagedEpisodeError, StagingArea, export_lerobot_dataset
    from rtv3_maniskill.scene_pool import SceneWorkerError, run_scenes

    try:  # refuses a folder with attempts made under other settings (not one whose run failed before any)
        with StagingArea(args.output, settings=_settings(args)) as staging:
            attempted = staging.attempts()
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    scenes = [] if args.export_only else scene_seeds(args.seed, args.num_scenes)
    jobs = [(s, sorted(k for k in attempted if k.startswith(StagingArea.scene_prefix(s)))) for s in scenes]
    if attempted:
        print(f"resuming: {len(attempted)} grasp targets already attempted in {args.output}")
    args_dict = {k: v for k, v in vars(args).items() if not k.startswith("_") and not callable(v)}
    args_dict["output"] = str(args.output)
    args_dict["write_through"] = args.workers == 1 and args.executor == "local"
    total: Counter = Counter()
    frames, seconds = 0, 0.0
    start = time.perf_counter()
    bar = tqdm(total=len(jobs), desc="scenes", unit="scene")
    results = run_scenes(_init_worker, args_dict, _run_scene, jobs, workers=args.workers, executor=args.executor,
                         ray_address=args.ray_address)
    try:
        with StagingArea(args.output) as staging:
            for result in results:
                if result["staged"] is not None:
                    staging.write(result["staged"])
                total.update(result["outcomes"])
                frames += result["frames"]
                seconds += result["seconds"]
                bar.update(1)
                bar.set_postfix(ok=total["success"], failed=sum(v for k, v in total.items() if k != "success"))
    except SceneWorkerError as err:
        raise SystemExit(f"error: {err}") from None
    finally:
        bar.close()
    wall = time.perf_counter() - start
    try:
        exported = export_lerobot_dataset(args.output, args.num_points, args.max_grasps, end_at=args.end_at)
    except StagedEpisodeError as err:
        raise SystemExit(f"error: {err}") from None
    # Summary over the whole folder (this run and earlier, interrupted ones).
    all_attempts = staging.attempts()
    outcome_counts = Counter(r["outcome"] for r in all_attempts.values())
    ok = outcome_counts.get("success", 0)
    data_bytes = sum(p.stat().st_size for p in (args.output / "data").rglob("*") if p.is_file())
    summary = dict(
        scenes=len({r["scene"] for r in all_attempts.values()}),
        grasp_targets_attempted=len(all_attempts),
        trajectories=ok,
        failures=dict((k, v) for k, v in outcome_counts.items() if k != "success"),
        success_rate_over_feasible_targets=ok / max(1, len(all_attempts) - outcome_counts.get("infeasible_target", 0)),
        frames=exported,
        dataset_bytes=data_bytes,
        bytes_per_frame=data_bytes / max(1, exported),
        this_run_trajectories=total["success"],
        this_run_wall_s=wall,
        this_run_cpu_worker_s=seconds,
        trajectories_per_core_hour=total["success"] / max(seconds, 1e-9) * 3600,
    )
    (args.output / "rtv3_summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    push_if_asked(args, args.output, "Motion-planner demonstrations (OMPL RRT-Connect + TOPP-RA)")
    return 0
