"""Training from a compact cache (``rtv3 compact-cache``; policies/rtv3/compact_cache.py and
compact_training.py): the cache holds what LeRobot's batches hold, its loss is lerobot-train's, the
trainer runs with PyTorch alone, resumes, and its checkpoint loads as an RT-V3 policy."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from test_policy_rtv3 import make_scene_batch

from rtv3_maniskill import features as ft
from rtv3_maniskill import se3
from rtv3_maniskill.cli import main
from rtv3_maniskill.policies.rtv3.compact_cache import CACHE_FILE, CompactCache, fit_budget, from_lerobot_dataset
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config

REPO = "local/rtv3_compact_test"
N, M, T = 64, 8, ft.HISTORY_STEPS


def _write_dataset(root, lengths=(9, 14, 6), scenes=(0, 0, 1), prefix_offsets=(0.0, 0.03, 0.0)):
    """Episodes with a stored state history, as ``rtv3 generate`` / ``rtv3 dagger`` write them: an
    episode's history before its first frame is its first state repeated (offset 0) or, as for a DAgger
    relabel, other states (the first state moved back along x by ``offset`` per step). Episodes of one
    scene share the scene context."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    feats = {
        ft.STATE: {"dtype": "float32", "shape": (ft.STATE_DIM,), "names": None},
        ft.STATE_HISTORY: {"dtype": "float32", "shape": ft.stored_shape(ft.STATE_HISTORY, T), "names": None},
        ft.POINT_CLOUD: {"dtype": "float32", "shape": ft.stored_shape(ft.POINT_CLOUD, N), "names": None},
        ft.POINT_CLOUD_MASK: {"dtype": "float32", "shape": (N,), "names": None},
        ft.GRASPS: {"dtype": "float32", "shape": ft.stored_shape(ft.GRASPS, M), "names": None},
        ft.GRASPS_MASK: {"dtype": "float32", "shape": (M,), "names": None},
        ft.ACTION: {"dtype": "float32", "shape": (6,), "names": None},
        ft.TARGET_GRASP: {"dtype": "int64", "shape": (1,), "names": None},
    }
    dataset = LeRobotDataset.create(REPO, fps=ft.FPS, features=feats, root=root, use_videos=False)
    long_cfg = RTV3Config(device="cpu", num_points=N, max_grasps=M, n_obs_steps=1, horizon=max(lengths))
    for episode, (length, scene, offset) in enumerate(zip(lengths, scenes, prefix_offsets)):
        context = make_scene_batch(long_cfg, batch=1, seed=40 + scene)
        motion = make_scene_batch(long_cfg, batch=1, seed=60 + episode)
        start = se3.pose_to_matrix(motion[ft.STATE][0, 0, 0:3], motion[ft.STATE][0, 0, 3:7])
        poses = torch.cat([start[None], se3.integrate_body_twists(start, motion[ft.ACTION][0], ft.DT)[:-1]])
        states = []
        for t in range(length):
            state = motion[ft.STATE][0, 0].clone()
            state[0:7] = se3.matrix_to_pose(poses[t])
            state[ft.EE_TWIST] = motion[ft.ACTION][0, max(t - 1, 0)]
            states.append(state)
        prefix = [states[0].clone() for _ in range(T - 1)]
        for j, p in enumerate(prefix):
            p[0] -= offset * (T - 1 - j)
        timeline = prefix + states
        for t in range(length):
            dataset.add_frame({
                ft.STATE: states[t],
                ft.STATE_HISTORY: torch.stack(timeline[t:t + T]).reshape(-1),
                ft.POINT_CLOUD: context[ft.POINT_CLOUD][0, 0].reshape(-1),
                ft.POINT_CLOUD_MASK: context[ft.POINT_CLOUD_MASK][0, 0],
                ft.GRASPS: context[ft.GRASPS][0, 0].reshape(-1),
                ft.GRASPS_MASK: context[ft.GRASPS_MASK][0, 0],
                ft.ACTION: motion[ft.ACTION][0, t],
                ft.TARGET_GRASP: torch.tensor([episode % 2], dtype=torch.int64),
                "task": "grasp",
            })
        dataset.save_episode()
    dataset.finalize()
    return dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return _write_dataset(tmp_path_factory.mktemp("compact") / "ds")


def test_compact_batches_and_loss_equal_lerobots(dataset):
    """Every frame: the cache gives LeRobot's stored history (a DAgger-style prefix included), its
    padded action window, the scene context and the target; the loss on those batches is the
    policy's loss on LeRobot's batches (eval mode: no augmentation)."""
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot.utils.import_utils import register_third_party_plugins

    from rtv3_maniskill.policies.rtv3.model import RTV3Model

    register_third_party_plugins()
    compact = from_lerobot_dataset(dataset.root)
    assert (compact.num_episodes, compact.num_frames) == (3, 29)
    assert compact.point_cloud.shape == (2, N, 6)  # two scenes: the shared context is stored once
    assert compact.episode_context.tolist() == [0, 0, 1] and compact.episode_target.tolist() == [0, 1, 0]

    cfg = RTV3Config(device="cpu", num_points=N, max_grasps=M)
    meta = dataset.meta
    lerobot_ds = LeRobotDataset(REPO, root=dataset.root, delta_timestamps=resolve_delta_timestamps(cfg, meta))
    torch.manual_seed(0)
    policy = make_policy(cfg, ds_meta=meta).eval()
    preprocessor, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    frames = torch.arange(compact.num_frames)
    batch = preprocessor(torch.utils.data.default_collate([lerobot_ds[i] for i in frames.tolist()]))
    inputs, actions, valid, target = compact.windows().batch(frames, cfg.horizon)
    lerobot_actions, lerobot_pad = policy.training_cache().action_windows(batch["index"], cfg.horizon)
    stored_history = ft.unflatten(ft.STATE_HISTORY, batch[ft.STATE_HISTORY])
    assert torch.equal(inputs.states, stored_history)
    assert not torch.equal(stored_history[9, 0], stored_history[9, 1])  # episode 1's prefix is not its first state
    assert torch.equal(actions, lerobot_actions) and torch.equal(valid, ~lerobot_pad)
    assert torch.equal(inputs.context.point_cloud, ft.unflatten(ft.POINT_CLOUD, batch[ft.POINT_CLOUD]))
    assert torch.equal(inputs.context.grasp_mask, batch[ft.GRASPS_MASK] > 0.5)
    assert torch.equal(target, batch[ft.TARGET_GRASP].reshape(-1))
    lerobot_loss = policy.forward({k: v for k, v in batch.items() if k != ft.TARGET_GRASP})[0]
    model = RTV3Model(policy.config).eval()
    model.load_state_dict(policy.model.state_dict())
    compact_loss = model(inputs, actions, valid, int(policy.train_step))[0]
    assert torch.allclose(compact_loss, lerobot_loss, rtol=1e-6, atol=1e-6)


def test_stored_history_that_is_not_the_episode_is_refused(tmp_path):
    """A frame whose stored history does not continue its episode cannot be rebuilt from the prefix:
    the export names the frame instead of training on a different history."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    ds = _write_dataset(tmp_path / "ds", lengths=(5,), scenes=(0,), prefix_offsets=(0.0,))
    path = next((ds.root / "data").rglob("*.parquet"))
    table = pq.read_table(path)
    column = table.column(ft.STATE_HISTORY).to_pylist()
    column[3] = [v + 0.5 for v in column[3]]
    index = table.schema.get_field_index(ft.STATE_HISTORY)
    table = table.set_column(index, table.schema.field(index), pa.array(column, type=table.schema.field(index).type))
    pq.write_table(table, path)
    with pytest.raises(ValueError, match="frame 3's stored"):
        from_lerobot_dataset(ds.root)


def test_budget_keeps_whole_episodes(dataset):
    compact = from_lerobot_dataset(dataset.root)
    assert fit_budget(compact, compact.nbytes()) is compact
    smaller = fit_budget(compact, compact.nbytes() - 1, seed=0)
    assert smaller.num_episodes == 2 and smaller.nbytes() < compact.nbytes()
    lengths = set(smaller.episode_length.tolist())
    assert lengths < {9, 14, 6} and smaller.num_frames == sum(smaller.episode_length.tolist())
    both = CompactCache.concatenate([compact, smaller])
    assert both.num_episodes == 5 and both.point_cloud.shape[0] == 4
    assert torch.equal(both.point_cloud[both.episode_context[3:]], smaller.point_cloud[smaller.episode_context])
    with pytest.raises(ValueError, match="episode_length"):
        CompactCache(**{**{f: getattr(compact, f) for f in compact.__dataclass_fields__},
                        "episode_length": compact.episode_length + 1})


@pytest.mark.sim
def test_build_train_without_lerobot_resume_and_finish(dataset, tmp_path):
    """``build`` here; ``train`` in a process where LeRobot cannot be imported (a bare GPU machine), 4
    steps then resumed to 6; ``finish`` makes the checkpoint a LeRobot folder the policy loads from."""
    from rtv3_maniskill.policies.rtv3 import load_policy

    cache = tmp_path / "cache"
    from rtv3_maniskill.policies.rtv3 import SHIPPED_CHECKPOINT

    assert main(["compact-cache", "build", "--dataset.root", str(dataset.root), "--output", str(cache),
                 "--policy.path", str(SHIPPED_CHECKPOINT), "--set", "optimizer_lr=0.0005"]) == 0
    summary = json.loads((cache / "summary.json").read_text())
    assert summary["episodes"] == 3 and summary["frames"] == 29 and summary["scene_contexts"] == 2
    saved = json.loads((cache / "config.json").read_text())
    assert saved["type"] == "rtv3" and saved["optimizer_lr"] == 0.0005 and saved["num_points"] == N

    script = ("import sys; sys.modules['lerobot'] = None; sys.modules['mani_skill'] = None; "
              "import runpy; sys.argv = ['compact_cache'] + sys.argv[1:]; "
              "runpy.run_module('rtv3_maniskill.cli.compact_cache', run_name='__main__')")
    run = tmp_path / "run"

    def train(steps):
        out = subprocess.run([sys.executable, "-c", script, "train", "--cache", str(cache), "--output", str(run),
                              "--steps", str(steps), "--batch-size", "8", "--save-freq", "2", "--log-freq", "1"],
                             capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=600)
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout[out.stdout.index("{"):])

    first = train(4)
    assert first["steps_run"] == 4 and np.isfinite(first["last_loss"])
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["000002", "000004", "last"]
    resumed = train(6)
    assert resumed["steps_run"] == 2 and resumed["final_step"] == 6
    assert main(["compact-cache", "finish", str(run / "checkpoints" / "last")]) == 0
    assert (run / "checkpoints" / "last" / "policy_preprocessor.json").is_file()
    policy = load_policy(run / "checkpoints" / "last")
    shipped = load_policy()
    assert int(policy.train_step) == int(shipped.train_step) + 6 and policy.config.optimizer_lr == 0.0005
    # fine-tuned from the shipped weights: changed by the steps, but not far
    change = [(a - b).abs().max() for a, b in zip(policy.parameters(), shipped.parameters())]
    assert 0 < max(change) < 0.05
    batch = make_scene_batch(policy.config, batch=2, seed=3)
    twist = policy.select_action({k: v[:, -1] if k == ft.STATE else v for k, v in batch.items() if k != ft.ACTION})
    assert twist.shape == (2, 6) and bool(torch.isfinite(twist).all())


@pytest.mark.sim
def test_gpu_recipe_script_trains_and_brings_the_weights_back(dataset, tmp_path):
    """``scripts/train_compact_gpu.sh`` (the command the GPU machine runs), here with DEVICE=cpu: it
    trains into RUN and copies the config, every checkpoint's weights and the log to $OUT."""
    cache, out = tmp_path / "cache", tmp_path / "out"
    out.mkdir()
    cache.mkdir()
    from_lerobot_dataset(dataset.root).save(cache / CACHE_FILE)
    RTV3Config(device="cpu", num_points=N, max_grasps=M)._save_pretrained(cache)
    assert CompactCache.load(cache / CACHE_FILE).num_frames == 29
    script = os.path.join(os.path.dirname(__file__), "..", "..", "scripts", "train_compact_gpu.sh")
    env = {**os.environ, "DEVICE": "cpu", "PYTHON": sys.executable, "OUT": str(out), "THROUGHPUT_BATCHES": "4",
           "THROUGHPUT_STEPS": "2", "OMP_NUM_THREADS": "1"}
    result = subprocess.run(["bash", script, str(cache), str(tmp_path / "run"), "--steps", "4", "--batch-size", "4",
                             "--save-freq", "2"], capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "device cpu" in result.stdout
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "logs.json", "model_000002.safetensors",
                                                     "model_000004.safetensors"]
    assert json.loads((out / "config.json").read_text())["type"] == "rtv3"


def test_bad_cache_inputs_name_the_problem(tmp_path, dataset):
    from rtv3_maniskill.policies.rtv3.compact_training import train

    with pytest.raises(FileNotFoundError, match="config.json"):
        train(tmp_path, tmp_path / "run", steps=1)
    (tmp_path / "config.json").write_text(json.dumps({"type": "act"}))
    with pytest.raises(ValueError, match="'act'"):
        train(tmp_path, tmp_path / "run", steps=1)
    with pytest.raises(FileNotFoundError, match="no compact training cache"):
        CompactCache.load(tmp_path / CACHE_FILE)
    with pytest.raises(FileNotFoundError, match="meta/info.json"):
        from_lerobot_dataset(tmp_path)
    with pytest.raises(SystemExit, match="positive"):
        main(["compact-cache", "build", "--dataset.root", str(dataset.root), "--output", str(tmp_path / "c"),
              "--max-mib", "0"])
