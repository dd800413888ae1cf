"""Checkpoints by Hub repo id: resolved through the Hugging Face cache, offline, everywhere a folder works."""

from __future__ import annotations

import csv
import json
import shutil

import pytest
import torch

from rtv3_maniskill.cli import main
from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT, CheckpointError, load_policy

REPO = "someone/rtv3"


@pytest.fixture()
def offline_cache(tmp_path, monkeypatch):
    """The shipped checkpoint laid out in a Hugging Face cache as the model repo ``someone/rtv3``, offline."""
    from huggingface_hub import constants

    cache = tmp_path / "hub"
    commit = "0" * 40
    snapshot = cache / "models--someone--rtv3" / "snapshots" / commit
    snapshot.mkdir(parents=True)
    for name in ("config.json", "model.safetensors"):
        shutil.copyfile(SHIPPED_CHECKPOINT / name, snapshot / name)
    (cache / "models--someone--rtv3" / "refs").mkdir()
    (cache / "models--someone--rtv3" / "refs" / "main").write_text(commit)
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    return snapshot


def test_load_policy_takes_a_repo_id_from_the_offline_cache(offline_cache):
    policy, shipped = load_policy(REPO), load_policy()
    for (name, a), (_, b) in zip(policy.state_dict().items(), shipped.state_dict().items()):
        assert torch.equal(a, b), name
    with pytest.raises(CheckpointError, match="not in the Hugging Face cache.*hf download someone/other"):
        load_policy("someone/other")


@pytest.mark.sim
def test_commands_take_a_repo_id(offline_cache, tmp_path):
    out = tmp_path / "bench"
    assert main(["benchmark-shared", "--policy.path", REPO, "--scenes", "1", "--goals-per-scene", "1", "--users",
                 "noisy", "--methods", "rtv3", "--output", str(out), "--no-progress"]) == 0
    with open(out / "results.csv") as f:
        assert len(list(csv.DictReader(f))) == 1
    assert json.loads((out / "config.json").read_text())["policy_path"] == str(offline_cache.resolve())
    plan = tmp_path / "plan"
    assert main(["evaluate", "planning", "--policy.path", REPO, "--scenes", "2", "--max-grasps-per-scene", "1",
                 "--output", str(plan)]) == 0
    assert json.loads((plan / "planning_summary.json").read_text())["trials"] >= 1
    with pytest.raises(SystemExit, match="not in the Hugging Face cache"):
        main(["benchmark-shared", "--policy.path", "someone/other", "--scenes", "1", "--users", "noisy",
              "--methods", "rtv3", "--output", str(tmp_path / "b2"), "--no-progress"])
