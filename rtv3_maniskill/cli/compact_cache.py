"""``rtv3 compact-cache``: train the RT-V3 prior from a compact cache, e.g. on a GPU machine.

Three steps (README, "Training on a GPU"):

* ``build`` (here, with LeRobot): a LeRobot dataset -> a folder with ``cache.npz`` (each scene
  context once, each episode's states and actions), the ``config.json`` to train and, with
  ``--policy.path``, the starting weights; at most ``--max-mib`` (a seeded subset of whole
  episodes when the dataset is larger).
* ``train`` (anywhere with PyTorch; no LeRobot or ManiSkill needed, so a bare GPU machine runs
  ``python -m rtv3_maniskill.cli.compact_cache train ...``): checkpoints every ``--save-freq``
  steps, resumed by rerunning the same command.
* ``finish`` (here): adds LeRobot's processor files and the model card to a trained checkpoint, so
  that ``lerobot-eval`` and ``push_to_hub`` take it like any ``lerobot-train`` checkpoint.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="step", metavar="STEP", required=True)
    build = sub.add_parser("build", help="LeRobot dataset -> compact cache folder (needs LeRobot)")
    build.add_argument("--dataset.root", dest="dataset_roots", type=Path, required=True, action="append",
                       help="LeRobot dataset folder (repeat it to train on several without merging them)")
    build.add_argument("--output", type=Path, required=True, help="cache folder to write")
    build.add_argument("--policy.path", dest="policy_path", type=Path, default=None,
                       help="checkpoint whose config and weights start the run (default: a fresh RTV3Config)")
    build.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                       help="change an RTV3Config field, e.g. --set optimizer_lr=3e-4 (JSON value; repeatable)")
    build.add_argument("--max-mib", type=float, default=60.0,
                       help="size limit of the cache in memory; a larger dataset keeps a seeded subset of episodes")
    build.add_argument("--seed", type=int, default=0, help="seed of that subset")
    _add_train_arguments(sub.add_parser("train", help="train from a cache folder (PyTorch alone)"))
    finish = sub.add_parser("finish", help="make a trained checkpoint a full LeRobot pretrained_model folder")
    finish.add_argument("checkpoint", type=Path, help="a checkpoint folder written by `train`")


def _add_train_arguments(train: argparse.ArgumentParser) -> None:
    train.add_argument("--cache", type=Path, required=True, help="folder written by `build`")
    train.add_argument("--output", type=Path, required=True, help="run folder (checkpoints/NNNNNN and last)")
    train.add_argument("--steps", type=int, required=True, help="training steps in all (a resumed run counts on)")
    train.add_argument("--batch-size", type=int, default=64)
    train.add_argument("--device", default="cpu", help="torch device, e.g. cuda")
    train.add_argument("--save-freq", type=int, default=1000)
    train.add_argument("--log-freq", type=int, default=50)
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--lr", type=float, default=None, help="learning rate (default: the config's)")
    train.add_argument("--lr-decay", type=float, default=None, help="per-step decay (default: the config's)")
    train.add_argument("--min-lr", type=float, default=None, help="learning-rate floor (default: the config's)")
    train.add_argument("--time-limit-min", type=float, default=None,
                       help="stop with a checkpoint after this many minutes (rerun to go on)")


def _build(args: argparse.Namespace) -> dict:
    import dataclasses

    from lerobot.configs.policies import PreTrainedConfig

    from rtv3_maniskill.policies.rtv3.compact_cache import (
        CACHE_FILE,
        INIT_WEIGHTS_FILE,
        SUMMARY_FILE,
        CompactCache,
        fit_budget,
        from_lerobot_dataset,
    )
    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config

    if args.max_mib <= 0:
        raise SystemExit(f"error: --max-mib must be positive, got {args.max_mib}")
    if args.policy_path is not None:
        from rtv3_maniskill.policies.rtv3.checkpoints import CheckpointError, resolve_checkpoint

        try:  # a folder or a Hub repo id
            args.policy_path = resolve_checkpoint(args.policy_path)
        except CheckpointError as err:
            raise SystemExit(f"error: {err}") from None
        config = PreTrainedConfig.from_pretrained(args.policy_path)
        if not isinstance(config, RTV3Config):
            raise SystemExit(f"error: --policy.path {args.policy_path} is a '{config.type}' policy, not 'rtv3'")
    else:
        config = RTV3Config()
    names = {f.name for f in dataclasses.fields(RTV3Config)}
    changes = {}
    for item in args.overrides:
        key, sep, text = item.partition("=")
        if not sep or key not in names:
            raise SystemExit(f"error: --set {item!r}: expected FIELD=VALUE with FIELD an RTV3Config field")
        try:
            changes[key] = json.loads(text)
        except json.JSONDecodeError:
            changes[key] = text
    try:
        compact = CompactCache.concatenate([from_lerobot_dataset(root, config.n_obs_steps)
                                            for root in args.dataset_roots])
        changes.setdefault("num_points", int(compact.point_cloud.shape[1]))
        changes.setdefault("max_grasps", int(compact.grasps.shape[1]))
        changes.update(device="cpu", init_weights_from=None, input_features={}, output_features={})
        config = dataclasses.replace(config, **changes)
        config.input_features = config.default_input_features()
        config.output_features = config.default_output_features()
        total = compact.num_episodes
        compact = fit_budget(compact, int(args.max_mib * 2**20), args.seed)
    except (ValueError, FileNotFoundError) as err:
        raise SystemExit(f"error: {err}") from None
    args.output.mkdir(parents=True, exist_ok=True)
    compact.save(args.output / CACHE_FILE)
    config._save_pretrained(args.output)
    if args.policy_path is not None:
        shutil.copyfile(args.policy_path / "model.safetensors", args.output / INIT_WEIGHTS_FILE)
    summary = {"datasets": [str(root) for root in args.dataset_roots], "episodes": compact.num_episodes,
               "dataset_episodes": total,
               "frames": compact.num_frames, "scene_contexts": int(compact.point_cloud.shape[0]),
               "in_memory_mib": round(compact.nbytes() / 2**20, 2),
               "folder_mib": round(sum(p.stat().st_size for p in args.output.iterdir()) / 2**20, 2),
               "init": str(args.policy_path) if args.policy_path else None}
    (args.output / SUMMARY_FILE).write_text(json.dumps(summary, indent=2))
    return summary


def _train(args: argparse.Namespace) -> dict:
    from rtv3_maniskill.policies.rtv3.compact_training import train

    try:
        result = train(args.cache, args.output, args.steps, args.batch_size, args.device, args.save_freq,
                       args.log_freq, args.seed, args.lr, args.lr_decay, args.min_lr,
                       None if args.time_limit_min is None else 60 * args.time_limit_min)
    except (ValueError, FileNotFoundError) as err:
        raise SystemExit(f"error: {err}") from None
    return {"steps_run": result.steps, "final_step": result.final_step, "last_loss": result.last_loss,
            "samples_per_s": round(result.samples_per_s, 1), "checkpoint": str(result.checkpoint),
            "device": args.device, "batch_size": args.batch_size}


def _finish(args: argparse.Namespace) -> dict:
    from rtv3_maniskill.policies.rtv3.checkpoints import load_policy
    from rtv3_maniskill.policies.rtv3.processor_rtv3 import make_rtv3_pre_post_processors

    try:
        policy = load_policy(args.checkpoint)
    except FileNotFoundError as err:
        raise SystemExit(f"error: {err}") from None
    policy.save_pretrained(args.checkpoint)
    for pipeline in make_rtv3_pre_post_processors(policy.config):
        pipeline.save_pretrained(args.checkpoint)
    return {"checkpoint": str(args.checkpoint), "train_step": int(policy.train_step)}


def run(args: argparse.Namespace) -> int:
    step = {"build": _build, "train": _train, "finish": _finish}[args.step]
    print(json.dumps(step(args), indent=2))
    return 0


if __name__ == "__main__":  # `python -m rtv3_maniskill.cli.compact_cache train ...` on a machine with PyTorch alone
    parser = argparse.ArgumentParser(prog="python -m rtv3_maniskill.cli.compact_cache")
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
