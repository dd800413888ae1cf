"""The rtv3 training cache (policies/rtv3/training_cache.py): LeRobot loads one row per sample and the
policy cuts the action / state windows from memory. The windows and the loss equal those of LeRobot's
own windows; ``lerobot-train`` resumes from its periodic checkpoints."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch
from test_policy_rtv3 import _write_dataset

from rtv3_maniskill import features as ft
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

REPO = "local/rtv3_test"


def test_cached_windows_and_loss_equal_lerobots_windows(tmp_path):
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    # a dataset without observation.state_history: the cache also gives the state history
    meta = _write_dataset(tmp_path / "ds", RTV3Config(device="cpu", num_points=64, max_grasps=8), frames=16).meta
    frames = [0, 1, 3, 7, 8, 14, 15, 16, 17, 25, 30, 31]  # episode starts and ends: padded windows
    # LeRobot's own windows: T history frames of every observation key, H future actions
    lerobot_windows = {key: [i / meta.fps for i in range(-ft.HISTORY_STEPS + 1, 1)]
                       for key in meta.features if key.startswith("observation.")}
    lerobot_windows[ft.ACTION] = [i / meta.fps for i in range(ft.HORIZON_STEPS)]
    losses, batches = {}, {}
    for cache in (False, True):
        cfg = RTV3Config(device="cpu")
        delta_timestamps = resolve_delta_timestamps(cfg, meta) if cache else lerobot_windows
        dataset = LeRobotDataset(REPO, root=tmp_path / "ds", delta_timestamps=delta_timestamps)
        torch.manual_seed(0)
        policy = make_policy(cfg, ds_meta=meta)
        preprocessor, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
        batches[cache] = preprocessor(torch.utils.data.default_collate([dataset[i] for i in frames]))
        policy.eval()  # no dropout / augmentation: the two losses must agree
        losses[cache] = policy.forward(batches[cache])[0]
    windowed, single = batches[False], batches[True]
    assert windowed[ft.ACTION].shape == (12, 12, 6) and single[ft.ACTION].shape == (12, 6)
    cache = policy.training_cache()
    actions, pad = cache.action_windows(single["index"], 12)
    assert torch.equal(actions, windowed[ft.ACTION]) and torch.equal(pad, windowed[f"{ft.ACTION}_is_pad"])
    assert torch.equal(cache.state_windows(single["index"], 8), windowed[ft.STATE])
    assert torch.allclose(losses[True], losses[False], rtol=1e-6, atol=1e-6)

    # A policy made without the dataset cannot cut windows: the error names the way out.
    bare = RTV3Policy(RTV3Config(device="cpu", num_points=64, max_grasps=8))
    try:
        bare.forward(single)
        raise AssertionError("expected a ValueError")
    except ValueError as err:
        assert "ds_meta" in str(err)


@pytest.mark.sim
def test_lerobot_train_resumes_from_its_last_checkpoint(tmp_path):
    """``lerobot-train --save_freq=N`` then ``--resume=true --config_path=.../train_config.json``: the run goes
    on from the saved step (optimizer, scheduler, the policy's own step counter) with the training cache."""
    _write_dataset(tmp_path / "ds", RTV3Config(device="cpu", num_points=64, max_grasps=8), frames=16)
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    train = [sys.executable, "-m", "lerobot.scripts.lerobot_train"]
    first = train + [
        f"--dataset.repo_id={REPO}", f"--dataset.root={tmp_path / 'ds'}", "--policy.type=rtv3", "--policy.device=cpu",
        "--policy.push_to_hub=false", "--steps=2", "--batch_size=4",
        "--num_workers=0", "--save_freq=1", f"--output_dir={out}", "--wandb.enable=false",
    ]
    run = subprocess.run(first, capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    last = out / "checkpoints" / "last" / "pretrained_model"
    assert int(RTV3Policy.from_pretrained(last).train_step) == 2
    resume = train + [f"--config_path={last / 'train_config.json'}", "--resume=true", "--steps=3"]
    run = subprocess.run(resume, capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    saved = json.loads((out / "checkpoints" / "last" / "training_state" / "training_step.json").read_text())
    assert saved["step"] == 3
    resumed = RTV3Policy.from_pretrained(out / "checkpoints" / "last" / "pretrained_model")
    assert int(resumed.train_step) == 3  # 2 steps, then 1 more: the counter came back from the checkpoint
