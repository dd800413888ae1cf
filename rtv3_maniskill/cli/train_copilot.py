"""``rtv3 train-copilot DATA... --output RUN``: train the diffusion copilot with ``lerobot-train``.

The recipe of the ``copilot`` method's checkpoint: LeRobot's own ``DiffusionPolicy`` on planner
demonstrations (the state and the scene summary ``observation.environment_state`` in, the 6-D body twist
out), small enough to train on two CPU cores in about an hour and to step well inside the 20 Hz loop.
Several datasets, or one written before the scene summary existed, are first merged into
``RUN/data`` (``rtv3 merge``). Rerunning the same command resumes from the last checkpoint; a finished
run is left as it is. The trained policy is ``RUN/train/checkpoints/last/pretrained_model``:
``rtv3 benchmark-shared --methods copilot --copilot-path`` and ``rtv3 teleop --method copilot
--copilot-path`` take it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from rtv3_maniskill import features
from rtv3_maniskill.features import REPO_ID
from rtv3_maniskill.records import claim_folder

POLICY_FLAGS = (
    "--policy.type=diffusion", "--policy.n_obs_steps=1", "--policy.horizon=8", "--policy.n_action_steps=4",
    "--policy.down_dims=[64,128]", "--policy.diffusion_step_embed_dim=64", "--policy.noise_scheduler_type=DDIM",
    "--policy.num_inference_steps=10",
)
"""The copilot's architecture: one observation step, an 8-step (0.4 s) action horizon, a two-level 1-D U-Net
(2.4 M parameters) and a DDIM schedule of 10 reverse steps."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("datasets", nargs="+", type=Path, metavar="DATA",
                        help="planner-demonstration datasets (rtv3 generate / rtv3 dagger --output)")
    parser.add_argument("--output", type=Path, required=True, help="the run's folder (resumed when it exists)")
    parser.add_argument("--steps", type=int, default=30_000, help="training steps (default 30000)")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--save-freq", type=int, default=2_000, help="checkpoint every this many steps")
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")


COPILOT_FEATURES = (features.STATE, features.ENV_STATE, features.ACTION)
"""What the copilot reads; the training copy keeps only these (and LeRobot's index columns): a frame of the
point cloud and grasps would be read 8 times per sample (the action horizon), 6x slower training on CPU."""


def training_data(datasets: list[Path], output: Path) -> Path:
    """The one dataset to train on, ``output/data`` (made once): the datasets merged (``rtv3 merge``, which adds
    the scene summary where it is missing) and cut to ``COPILOT_FEATURES``."""
    from lerobot.datasets.dataset_tools import remove_feature  # LeRobot: loaded when the command runs
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.datagen.merge import has_scene_summary, merge

    data = output / "data"
    if (data / "meta" / "info.json").is_file():
        return data
    merged_root = output / ".merged"
    shutil.rmtree(merged_root, ignore_errors=True)  # left by a run that was killed
    shutil.rmtree(data, ignore_errors=True)
    if len(datasets) == 1 and has_scene_summary(datasets[0]):
        merged = LeRobotDataset(REPO_ID, root=datasets[0])
    else:
        merged, _ = merge(datasets, merged_root)
    extra = [k for k in merged.meta.features if k.startswith("observation.") and k not in COPILOT_FEATURES]
    try:
        remove_feature(merged, extra, output_dir=data, repo_id=REPO_ID)
    except BaseException:
        shutil.rmtree(data, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(merged_root, ignore_errors=True)
    return data


def trained_steps(run: Path) -> int:
    """The step of the run's last checkpoint (0: none)."""
    step = run / "checkpoints" / "last" / "training_state" / "training_step.json"
    return int(json.loads(step.read_text())["step"]) if step.is_file() else 0


def lerobot_train_command(data: Path, run: Path, steps: int, batch_size: int, save_freq: int, device: str) -> list[str]:
    """The ``lerobot-train`` command line of the copilot (resuming ``run`` when it holds a checkpoint)."""
    exe = str(Path(sys.executable).parent / "lerobot-train")
    last = run / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    if trained_steps(run) and last.is_file():
        return [exe, f"--config_path={last}", "--resume=true", f"--steps={steps}"]
    return [exe, f"--dataset.repo_id={REPO_ID}", f"--dataset.root={data}", *POLICY_FLAGS,
            f"--policy.device={device}", "--policy.push_to_hub=false", f"--steps={steps}", f"--batch_size={batch_size}",
            f"--save_freq={save_freq}", "--log_freq=200", "--num_workers=1", f"--output_dir={run}",
            "--wandb.enable=false", "--job_name=rtv3_copilot"]


def run(args: argparse.Namespace) -> int:
    missing = [str(d) for d in args.datasets if not (d / "meta" / "info.json").is_file()]
    if missing:
        raise SystemExit(f"error: not a LeRobot dataset (no meta/info.json): {', '.join(missing)}")
    args.output.mkdir(parents=True, exist_ok=True)
    with claim_folder(args.output):
        data = training_data(args.datasets, args.output)
        run_dir = args.output / "train"
        final = run_dir / "checkpoints" / "last" / "pretrained_model"
        if trained_steps(run_dir) >= args.steps:
            print(f"{final}: trained ({trained_steps(run_dir)} steps)")
            return 0
        if run_dir.exists() and trained_steps(run_dir) == 0:
            shutil.rmtree(run_dir)  # killed before its first checkpoint: nothing to resume
        cmd = lerobot_train_command(data, run_dir, args.steps, args.batch_size, args.save_freq, args.device)
        result = subprocess.run(cmd, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        if result.returncode:
            return result.returncode
        print(f"{final}: trained ({trained_steps(run_dir)} steps)")
    return 0
