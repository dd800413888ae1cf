"""`rtv3 generate`: planner demonstrations end to end into a LeRobot dataset, resumable."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.cli import main
from rtv3_maniskill.datagen.demonstrations import HOLD_STEPS
from rtv3_maniskill.datagen.lerobot_export import (
    ATTEMPT_FIELDS,
    ATTEMPTS,
    SETTINGS,
    StagingArea,
    end_at_pregrasp,
)
from rtv3_maniskill.features import PREGRASP_DISTANCE, REPO_ID
from rtv3_maniskill.records import RecordStore

ARGS = ["--num-points", "256", "--max-grasps", "16", "--context", "mesh", "--scene-type", "packed"]


def _windows() -> dict[str, list[float]]:
    past = [i / features.FPS for i in range(-features.HISTORY_STEPS + 1, 1)]
    keys = [features.STATE, features.STATE_HISTORY, features.POINT_CLOUD, features.POINT_CLOUD_MASK, features.GRASPS,
            features.GRASPS_MASK]
    out = {k: past for k in keys}
    out[features.ACTION] = [i / features.FPS for i in range(features.HORIZON_STEPS)]
    return out


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("gen") / "ds"
    assert main(["generate", "--num-scenes", "1", "--output", str(root), "--grasps-per-scene", "3", *ARGS]) == 0
    return root


@pytest.mark.sim
def test_tiny_generation_loads_with_training_windows(tiny_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    summary = json.loads((tiny_dataset / "rtv3_summary.json").read_text())
    assert summary["trajectories"] >= 1
    assert summary["grasp_targets_attempted"] == 3
    ds = LeRobotDataset(REPO_ID, root=tiny_dataset, delta_timestamps=_windows())
    assert ds.num_episodes == summary["trajectories"]
    assert ds.fps == features.FPS
    item = ds[len(ds) // 2]
    assert item[features.STATE].shape == (features.HISTORY_STEPS, features.STATE_DIM)
    # stored flat (LeRobot's dataset tools copy only 1-D features); features.unflatten restores them
    assert item[features.POINT_CLOUD].shape == (features.HISTORY_STEPS, 256 * 6)
    assert (features.unflatten(features.POINT_CLOUD, item[features.POINT_CLOUD]).shape
            == (features.HISTORY_STEPS, 256, 6))
    assert (features.unflatten(features.GRASPS, item[features.GRASPS]).shape
            == (features.HISTORY_STEPS, 16, features.GRASP_DIM))
    assert item[features.STATE_HISTORY].shape == (features.HISTORY_STEPS, features.HISTORY_STEPS * features.STATE_DIM)
    assert item[features.ACTION].shape == (features.HORIZON_STEPS, 6)
    assert item["task"].startswith("grasp the ")


@pytest.mark.sim
def test_actions_are_the_realised_twists(tiny_dataset):
    """Integrating action t from the pose at t gives the recorded pose at t+1 (frames agree)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=tiny_dataset, episodes=[0])
    state = torch.stack([ds[i][features.STATE] for i in range(len(ds))]).double()
    action = torch.stack([ds[i][features.ACTION] for i in range(len(ds))]).double()
    poses = se3.pose_to_matrix(state[:, features.EE_POS], state[:, features.EE_QUAT])
    predicted = poses[:-1] @ se3.se3_exp(action[:-1] * features.DT)
    assert (predicted[:, :3, 3] - poses[1:, :3, 3]).abs().max() < 1e-4
    # The episode ends holding still (zero twist), as the model must learn to stop.
    assert action[-10:].abs().max() < 0.02


@pytest.mark.sim
def test_episode_ends_holding_at_the_pregrasp(tiny_dataset):
    """Default ``--end-at pregrasp`` (paper): the demonstration stops at the target's pre-grasp."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=tiny_dataset, episodes=[0])
    reached = torch.stack([ds[i]["pregrasp_reached"] for i in range(len(ds))]).reshape(-1)
    assert not bool(reached[0]) and bool(reached[-1])
    assert int(reached.sum()) == HOLD_STEPS + 1
    last = ds[len(ds) - 1]
    grasp = features.unflatten(features.GRASPS, last[features.GRASPS])[int(last[features.TARGET_GRASP])].double()
    pose = se3.pose_to_matrix(grasp[None, :3], grasp[None, 3:7])
    pregrasp = se3.translate_along_z(pose, -PREGRASP_DISTANCE)[0, :3, 3]
    assert (last[features.STATE][features.EE_POS].double() - pregrasp).norm() < 0.015


def test_end_at_pregrasp_cuts_a_staged_approach():
    """Episodes staged with the approach (``--end-at grasp``) export cut at the pre-grasp + copies at rest."""
    rng = np.random.default_rng(0)
    state, action = (rng.normal(size=(40, features.STATE_DIM)).astype(np.float32),
                     rng.normal(size=(40, 6)).astype(np.float32))
    cut_state, cut_action = end_at_pregrasp(state, action, pregrasp_step=20)
    assert cut_state.shape == (21 + HOLD_STEPS, features.STATE_DIM) and cut_action.shape == (21 + HOLD_STEPS, 6)
    np.testing.assert_array_equal(cut_state[:21], state[:21])
    np.testing.assert_array_equal(cut_action[:20], action[:20])
    assert not cut_action[20:].any()
    held = cut_state[21:]
    np.testing.assert_array_equal(held[:, features.EE_POS], np.repeat(state[20:21, features.EE_POS], HOLD_STEPS, 0))
    assert not held[:, features.EE_TWIST].any() and not held[:, features.ARM_QVEL].any()
    with pytest.raises(ValueError, match="pregrasp_step"):
        end_at_pregrasp(state, action, pregrasp_step=40)


@pytest.mark.sim
def test_interrupted_run_resumes_without_duplicates(tmp_path):
    root = tmp_path / "ds"
    cmd = [sys.executable, "-m", "rtv3_maniskill.cli", "generate", "--num-scenes", "1", "--output", str(root),
           "--grasps-per-scene", "6", *ARGS]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env=dict(os.environ, PYTHONWARNINGS="ignore"))
    staging = root / "rtv3_staging"
    deadline = time.time() + 240
    while time.time() < deadline and not list(staging.glob("scene*_grasp*.npz")):
        time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = StagingArea(root).attempts()
    assert first, "the first run should have finished at least one episode before the kill"
    assert len(first) < 6, "the kill should land before the run finished"
    assert main(["generate", "--num-scenes", "1", "--output", str(root), "--grasps-per-scene", "6", *ARGS]) == 0
    attempts = StagingArea(root).attempts()
    assert len(attempts) == 6  # every (scene, grasp) exactly once
    keys = [row["key"] for row in RecordStore.read(staging / ATTEMPTS, ATTEMPT_FIELDS)]
    assert len(keys) == len(set(keys)), "no grasp target was attempted twice"
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=root)
    ok = sum(1 for r in attempts.values() if r["outcome"] == "success")
    assert ds.num_episodes == ok
    assert not list(staging.glob("*.tmp.npz"))


@pytest.mark.sim
def test_bad_inputs_give_clear_errors(tmp_path, tiny_dataset):
    with pytest.raises(SystemExit, match="parent folder"):
        main(["generate", "--num-scenes", "1", "--output", str(tmp_path / "missing" / "ds")])
    with pytest.raises(SystemExit, match="num-scenes must be positive"):
        main(["generate", "--num-scenes", "0", "--output", str(tmp_path / "ds")])
    with pytest.raises(SystemExit, match="other settings"):
        main(["generate", "--num-scenes", "1", "--output", str(tiny_dataset), "--seed", "5", *ARGS])
    foreign = tmp_path / "foreign"
    (foreign / "meta").mkdir(parents=True)
    with pytest.raises(SystemExit, match="did not create"):
        main(["generate", "--num-scenes", "1", "--output", str(foreign), *ARGS])


@pytest.mark.sim
def test_failed_run_does_not_block_the_corrected_rerun(tmp_path):
    """A bad --objects is refused before anything is written; a folder whose earlier run failed
    before its first attempt (settings written, nothing recorded) takes a rerun with other settings."""
    root = tmp_path / "ds"
    with pytest.raises(SystemExit, match="--objects.*/nonexistent"):
        main(["generate", "--num-scenes", "1", "--output", str(root), "--objects", "/nonexistent", *ARGS])
    assert not root.exists()
    # A run that died after writing its settings, before recording any attempt:
    other = dict(format="rtv3-grasp-clutter-v1", seed=0, scene_type="packed", objects="/nonexistent",
                 num_points=256, max_grasps=16, context="mesh", end_at="pregrasp")
    StagingArea(root, settings=other).close()
    assert json.loads((root / SETTINGS).read_text())["objects"] == "/nonexistent"
    assert main(["generate", "--num-scenes", "1", "--output", str(root), "--grasps-per-scene", "3", *ARGS]) == 0
    assert json.loads((root / SETTINGS).read_text())["objects"] == "procedural"
    assert len(StagingArea(root).attempts()) == 3
    # ... and once attempts are recorded, other settings are refused
    with pytest.raises(SystemExit, match="other settings"):
        main(["generate", "--num-scenes", "1", "--output", str(root), "--seed", "7", *ARGS])


@pytest.mark.sim
def test_truncated_staged_episode_names_the_file(tiny_dataset, tmp_path):
    """A truncated staging .npz: a clear error naming the file and what to do; doing it works."""
    root = tmp_path / "ds"
    shutil.copytree(tiny_dataset, root)
    victim = StagingArea(root).episode_files()[0]
    episodes = len(StagingArea(root).episode_files())
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    with pytest.raises(SystemExit, match=rf"(?s){victim.name}.*Delete it and rerun"):
        main(["generate", "--num-scenes", "1", "--output", str(root), "--grasps-per-scene", "3", "--export-only",
              *ARGS])
    victim.unlink()
    assert main(["generate", "--num-scenes", "1", "--output", str(root), "--grasps-per-scene", "3", *ARGS]) == 0
    assert victim.exists() and len(StagingArea(root).episode_files()) == episodes
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    assert LeRobotDataset(REPO_ID, root=root).num_episodes == episodes


@pytest.mark.sim
def test_staged_episode_loads_as_an_episode(tiny_dataset):
    from rtv3_maniskill.datagen.demonstrations import Episode

    episode = StagingArea.load(StagingArea(tiny_dataset).episode_files()[0])
    assert isinstance(episode, Episode)
    assert episode.point_cloud.shape == (256, 6) and episode.grasps.shape == (16, features.GRASP_DIM)
    assert episode.task.startswith("grasp the ") and 0 < episode.pregrasp_step < len(episode.state)


@pytest.mark.sim
def test_visualize_episode(tiny_dataset, tmp_path):
    out = tmp_path / "episode.png"
    assert main(["visualize-episode", "--dataset", str(tiny_dataset), "--episode", "0", "--output", str(out)]) == 0
    assert out.stat().st_size > 10_000
    image = np.asarray(__import__("imageio").v3.imread(out))
    assert image.ndim == 3 and image.std() > 5


@pytest.mark.sim
def test_state_history_matches_the_episode(tiny_dataset):
    """The stored history is the last T states, the first repeated before the episode start."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=tiny_dataset, episodes=[0])
    states = torch.stack([ds[i][features.STATE] for i in range(len(ds))])
    for t in (0, 3, len(ds) - 1):
        history = features.unflatten(features.STATE_HISTORY, ds[t][features.STATE_HISTORY])
        expected = torch.stack([states[max(t - k, 0)] for k in range(features.HISTORY_STEPS - 1, -1, -1)])
        assert torch.equal(history, expected)


@pytest.mark.sim
def test_lerobot_train_on_generated_dataset(tiny_dataset, tmp_path):
    """`lerobot-train --policy.type=rtv3` on `rtv3 generate` output, no extra flag, then reload."""
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

    lerobot_train = Path(sys.executable).parent / "lerobot-train"
    out = tmp_path / "train"
    cmd = [
        str(lerobot_train), f"--dataset.repo_id={REPO_ID}", f"--dataset.root={tiny_dataset}", "--policy.type=rtv3",
        "--policy.push_to_hub=false", "--policy.device=cpu", "--steps=2", "--batch_size=2", "--num_workers=0",
        "--save_freq=2", f"--output_dir={out}", "--wandb.enable=false",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"), timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    policy = RTV3Policy.from_pretrained(checkpoint)
    assert policy.config.num_points == 256 and policy.config.max_grasps == 16

    # ... and `lerobot-eval` runs it in GraspClutter-v1 through the `rtv3_clutter` env config.
    lerobot_eval = Path(sys.executable).parent / "lerobot-eval"
    cmd = [
        str(lerobot_eval), f"--policy.path={checkpoint}", "--env.type=rtv3_clutter", "--env.num_points=256",
        "--env.max_grasps=16", "--env.episode_length=5", "--eval.n_episodes=1", "--eval.batch_size=1",
        "--policy.device=cpu", f"--output_dir={tmp_path / 'eval'}",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"), timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "pc_success" in result.stdout + result.stderr


def test_exact_episode_stats_match_lerobots_own():
    from lerobot.datasets.compute_stats import compute_episode_stats

    from rtv3_maniskill.datagen.episode_stats import exact_episode_stats
    from rtv3_maniskill.datagen.lerobot_export import dataset_features

    rng = np.random.default_rng(0)
    spec = dataset_features(num_points=32, max_grasps=4)
    spec["index"] = {"dtype": "int64", "shape": (1,)}
    spec["task"] = {"dtype": "string", "shape": (1,)}
    frames = 40
    episode = {key: rng.normal(size=(frames, *value["shape"])).astype(np.float32).reshape(frames, -1)
               for key, value in spec.items() if value["dtype"] == "float32"}
    episode["index"] = np.arange(frames)
    episode["pregrasp_reached"] = (np.arange(frames) > 30)[:, None]
    episode["task"] = ["grasp the box"] * frames
    spec = {k: v for k, v in spec.items() if k in episode}
    ours, theirs = exact_episode_stats(episode, spec), compute_episode_stats(episode, spec)
    assert set(ours) == set(theirs) and "task" not in ours
    for key, stats in theirs.items():
        assert set(ours[key]) == set(stats), key
        for name, value in stats.items():
            assert ours[key][name].shape == value.shape, (key, name)
            if name in ("min", "max", "mean", "std", "count"):
                np.testing.assert_allclose(ours[key][name], value, rtol=1e-5, atol=1e-6, err_msg=f"{key} {name}")
        # LeRobot's quantiles are histogram estimates (off by up to ~20 % of the range at 40 frames);
        # ours are exact: ordered, inside [min, max], the median the data's median
        levels = [ours[key][q] for q in ("min", "q01", "q10", "q50", "q90", "q99", "max")]
        assert all(np.all(a <= b + 1e-9) for a, b in zip(levels, levels[1:])), key
        data = np.asarray(episode[key], dtype=np.float64).reshape(frames, -1)
        np.testing.assert_allclose(ours[key]["q50"].reshape(-1), np.median(data, axis=0), atol=1e-9)


@pytest.mark.sim
def test_exported_dataset_stats_cover_every_frame(tiny_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=tiny_dataset)
    actions = np.stack([ds.hf_dataset[i][features.ACTION].numpy() for i in range(len(ds))])
    stats = ds.meta.stats[features.ACTION]
    np.testing.assert_allclose(stats["min"], actions.min(0), atol=1e-6)
    np.testing.assert_allclose(stats["max"], actions.max(0), atol=1e-6)
    np.testing.assert_allclose(stats["mean"], actions.mean(0), atol=1e-5)
    assert int(np.asarray(stats["count"]).item()) == len(ds)


@pytest.mark.sim
def test_info_json_says_the_layout_of_every_flat_feature_and_batches_unflatten(tiny_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    info = json.loads((tiny_dataset / "meta" / "info.json").read_text())["features"]
    for key, (item, channels) in features.FLAT_LAYOUTS.items():
        names = info[key]["names"]
        rows = names["rows"][1]
        assert names["rows"][0] == item and names["channels"] == list(channels)
        assert info[key]["shape"] == [rows * len(channels)]
    assert info[features.POINT_CLOUD]["names"]["channels"] == ["x", "y", "z", "r", "g", "b"]
    sample = LeRobotDataset(REPO_ID, root=tiny_dataset)[0]
    batch = features.unflatten_batch({k: v[None] for k, v in sample.items() if isinstance(v, torch.Tensor)})
    assert tuple(batch[features.POINT_CLOUD].shape) == (1, 256, 6)
    assert tuple(batch[features.GRASPS].shape) == (1, 16, features.GRASP_DIM)
    assert tuple(batch[features.STATE_HISTORY].shape) == (1, features.HISTORY_STEPS, features.STATE_DIM)
    assert batch[features.ACTION] is not None and tuple(batch[features.ACTION].shape) == (1, 6)


@pytest.mark.sim
def test_push_to_hub_uploads_the_dataset_with_a_card_and_fails_clearly_offline(tiny_dataset, tmp_path, monkeypatch):
    import huggingface_hub
    from huggingface_hub import constants

    from rtv3_maniskill.datagen.hub import HubPushError, push_dataset

    calls: dict[str, object] = {}
    monkeypatch.setattr(huggingface_hub.HfApi, "create_repo", lambda self, **kw: calls.setdefault("repo", kw))
    monkeypatch.setattr(huggingface_hub.HfApi, "upload_folder", lambda self, **kw: calls.setdefault("upload", kw))
    monkeypatch.setattr(huggingface_hub.HfApi, "create_tag", lambda self, *a, **kw: None)
    monkeypatch.setattr(huggingface_hub.HfApi, "delete_tag", lambda self, *a, **kw: None)
    monkeypatch.setattr(huggingface_hub.DatasetCard, "push_to_hub",
                        lambda self, **kw: calls.setdefault("card", str(self)))
    command = "rtv3 generate --num-scenes 1 --output ds --push-to-hub someone/grasps"
    assert push_dataset(tiny_dataset, "someone/grasps", "Motion-planner demonstrations", command) == "someone/grasps"
    assert calls["repo"]["repo_id"] == "someone/grasps" and calls["repo"]["repo_type"] == "dataset"
    assert Path(calls["upload"]["folder_path"]) == tiny_dataset and calls["upload"]["repo_type"] == "dataset"
    card = calls["card"]
    assert command in card and "GraspClutter-v1" in card and '"observation.point_cloud"' in card
    with pytest.raises(ValueError, match="not a Hub repo id"):
        push_dataset(tiny_dataset, "no-owner", "x")
    monkeypatch.undo()
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(HubPushError, match="could not push .* the dataset is kept there"):
        push_dataset(tiny_dataset, "someone/grasps", "Motion-planner demonstrations", command)


STOCK_POLICY_FLAGS = {
    "diffusion": ["--policy.down_dims=[32,64]", "--policy.horizon=8", "--policy.n_action_steps=4"],
    "act": ["--policy.dim_model=32", "--policy.dim_feedforward=64", "--policy.n_encoder_layers=1",
            "--policy.n_decoder_layers=1", "--policy.chunk_size=8", "--policy.n_action_steps=8"],
}


@pytest.mark.sim
@pytest.mark.parametrize("policy_type", sorted(STOCK_POLICY_FLAGS))
def test_stock_lerobot_policies_train_on_generated_dataset(tiny_dataset, tmp_path, policy_type):
    """LeRobot's own diffusion and ACT policies train on `rtv3 generate` output: the dataset's
    observation.environment_state (the scene summary) is the input they need beside the state."""
    info = json.loads((tiny_dataset / "meta" / "info.json").read_text())
    assert info["features"][features.ENV_STATE]["shape"] == [features.scene_summary_dim(16)]
    lerobot_train = Path(sys.executable).parent / "lerobot-train"
    out = tmp_path / "train"
    cmd = [
        str(lerobot_train), f"--dataset.repo_id={REPO_ID}", f"--dataset.root={tiny_dataset}",
        f"--policy.type={policy_type}", "--policy.push_to_hub=false", "--policy.device=cpu", "--steps=2",
        "--batch_size=2", "--num_workers=0", "--save_freq=2", f"--output_dir={out}", "--wandb.enable=false",
        *STOCK_POLICY_FLAGS[policy_type],
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"), timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    config = json.loads((out / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert config["input_features"][features.ENV_STATE]["type"] == "ENV"


@pytest.mark.sim
def test_train_copilot_trains_a_copilot_that_steps_and_resumes(tiny_dataset, tmp_path, capsys):
    """`rtv3 train-copilot` (lerobot-train's diffusion policy on a slim copy of the data) gives a checkpoint the
    copilot method loads and steps; a rerun of a finished run trains nothing more."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.cli.train_copilot import COPILOT_FEATURES, trained_steps
    from rtv3_maniskill.shared_control.copilot import DiffusionCopilot

    run = tmp_path / "copilot"
    args = ["train-copilot", str(tiny_dataset), "--output", str(run), "--steps", "2", "--batch-size", "2",
            "--save-freq", "2"]
    assert main(args) == 0
    data = json.loads((run / "data" / "meta" / "info.json").read_text())["features"]
    assert [k for k in data if k.startswith(("observation.", "action"))] == list(COPILOT_FEATURES)
    assert trained_steps(run / "train") == 2
    copilot = DiffusionCopilot.from_pretrained(run / "train" / "checkpoints" / "last" / "pretrained_model",
                                               gamma=0.5)
    assert copilot.max_grasps == 16
    frame = LeRobotDataset(REPO_ID, root=tiny_dataset)[0]
    observation = {k: frame[k][None] for k in (features.STATE, features.ENV_STATE, features.POINT_CLOUD,
                                               features.POINT_CLOUD_MASK, features.GRASPS, features.GRASPS_MASK)}
    twist = copilot.step(observation, torch.tensor([[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]]))
    assert twist.shape == (1, 6) and torch.isfinite(twist).all()
    capsys.readouterr()
    assert main(args) == 0
    assert "trained (2 steps)" in capsys.readouterr().out
