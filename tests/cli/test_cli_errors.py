"""Bad input to every `rtv3` subcommand: one `error:` line naming the problem, no traceback, the usual exit status."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT

pytestmark = pytest.mark.sim  # every test here runs the simulator

RTV3 = str(Path(sys.executable).with_name("rtv3"))


@pytest.fixture(scope="module")
def broken(tmp_path_factory) -> dict[str, Path]:
    """A truncated checkpoint, one whose config.json has an unknown field, an empty folder, a plain file."""
    root = tmp_path_factory.mktemp("broken")
    truncated, bad_config, empty = root / "truncated", root / "bad_config", root / "empty"
    for folder in (truncated, bad_config):
        shutil.copytree(SHIPPED_CHECKPOINT, folder)
    weights = truncated / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:4096])
    config = json.loads((bad_config / "config.json").read_text())
    config["no_such_field"] = 1
    (bad_config / "config.json").write_text(json.dumps(config))
    empty.mkdir()
    (root / "not_a_folder.txt").write_text("x")
    (root / "not_a_session" / "data" / "chunk-000").mkdir(parents=True)
    return dict(truncated=truncated, bad_config=bad_config, empty=empty, file=root / "not_a_folder.txt",
                not_a_session=root / "not_a_session")


CASES = [
    # (arguments, words the error line must hold, exit status)
    (["teleop", "--input", "simulated:nobody", "--headless"], "unknown simulated user 'nobody'", 2),
    (["teleop", "--input", "simulated:noisy", "--headless", "--timeout", "-5"], "--timeout must be a positive", 2),
    (["teleop", "--input", "gamepad"], "--input gamepad: no gamepad", 1),
    (["teleop", "--input", "simulated:noisy", "--headless", "--policy.path", "{empty}"], "missing config.json", 1),
    (["study", "plan", "--methods", "rtv3,bogus", "--output", "{tmp}/plan.csv"], "unknown method(s) bogus", 2),
    (["study", "plan", "--participants", "0", "--output", "{tmp}/plan.csv"], "--participants must be >= 1", 2),
    (["study", "analyze", "{empty}"], "sessions.csv is missing", 1),
    (["study", "analyze", "{not_a_session}"], "sessions.csv is missing", 1),
    (["benchmark-shared", "--output", "{file}", "--scenes", "1", "--methods", "direct"], "is a file, not a folder", 1),
    (["benchmark-shared", "--policy.path", "{empty}", "--output", "{tmp}/b1"], "missing config.json", 1),
    (["benchmark-shared", "--preset", "hard"], "invalid choice: 'hard'", 2),
    (["evaluate", "planning", "--policy.path", "{bad_config}", "--scenes", "1", "--output", "{tmp}/p1"],
     "config.json is not a readable RT-V3 config (DecodingError: The fields `no_such_field`", 1),
    (["demo", "--policy.path", "{truncated}", "--no-video"], "model.safetensors cannot be loaded", 1),
    (["dagger", "--policy.path", "{empty}", "--output", "{tmp}/d1"], "missing config.json", 1),
    (["generate", "--num-scenes", "1", "--output", "{tmp}/g1", "--objects", "ycb:banana"], "unknown YCB objects", 1),
    (["generate", "--num-scenes", "1", "--output", "{tmp}/g2", "--push-to-hub", "no-owner"], "not a Hub repo id", 1),
]


@pytest.mark.parametrize("argv, message, status", CASES, ids=[" ".join(c[0][:3]) for c in CASES])
def test_bad_input_gives_one_error_line(broken, tmp_path, argv, message, status):
    names = {**{k: str(v) for k, v in broken.items()}, "tmp": str(tmp_path)}
    proc = subprocess.run([RTV3, *(a.format(**names) for a in argv)], capture_output=True, text=True, timeout=300,
                          env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "PYTHONWARNINGS": "ignore",
                               "HF_HUB_OFFLINE": "1", "SDL_VIDEODRIVER": "dummy"})
    assert proc.returncode == status, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr + proc.stdout
    errors = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and message in errors[0], proc.stderr[-2000:]


def test_a_worker_pool_with_a_truncated_checkpoint_stops_at_once_naming_the_file(broken, tmp_path):
    start = time.monotonic()
    proc = subprocess.run([RTV3, "benchmark-shared", "--scenes", "2", "--goals-per-scene", "1", "--users", "noisy",
                           "--methods", "rtv3", "--workers", "2", "--no-progress", "--policy.path",
                           str(broken["truncated"]), "--output", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=300,
                          env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "PYTHONWARNINGS": "ignore"})
    assert proc.returncode == 1 and time.monotonic() - start < 120
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "model.safetensors cannot be loaded" in errors[0]
    assert str(broken["truncated"]) in errors[0] and "Traceback" not in proc.stderr


@pytest.mark.parametrize("index", [2.7, "a", float("nan")])
def test_a_target_index_that_is_not_a_whole_number_is_refused(index):
    import gymnasium as gym

    import rtv3_maniskill  # noqa: F401

    env = gym.make("GraspClutter-v1", obs_mode="state_dict", render_backend="none", scene_type="packed")
    try:
        with pytest.raises(ValueError, match="target_grasp_index must be a whole number"):
            env.reset(seed=0, options={"target_grasp_index": index})
    finally:
        env.close()
