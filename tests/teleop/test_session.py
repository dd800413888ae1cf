"""`rtv3 teleop`: a person at the keyboard (Xvfb + xdotool), the grasp buttons, the recorded LeRobot session."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from rtv3_maniskill import features
from rtv3_maniskill.teleop.devices import KeyboardMapping
from rtv3_maniskill.teleop.recorder import ASSIST_MODES, OUTCOMES, USER_TWIST

pytestmark = pytest.mark.sim  # every test here runs the simulator

REPO = Path(__file__).resolve().parents[2]
RTV3 = str(Path(sys.executable).with_name("rtv3"))


def _frames(folder: Path) -> pd.DataFrame:
    files = sorted((folder / "data").glob("*/*.parquet"))
    assert files, f"no LeRobot data in {folder}"
    return pd.concat([pd.read_parquet(f) for f in files])


def _start_xvfb() -> tuple[subprocess.Popen, str]:
    read, write = os.pipe()
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "1024x600x24", "-nolisten", "tcp"],
                            pass_fds=(write,), stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as f:
        number = f.readline().strip()
    assert number, "Xvfb did not report its display number"
    return xvfb, f":{number}"


def _xdotool(display: str, *args: str) -> str:
    out = subprocess.run(["xdotool", *args], env=dict(os.environ, DISPLAY=display), capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, f"xdotool {args} failed: {out.stderr}"
    return out.stdout.strip()


@pytest.mark.skipif(shutil.which("Xvfb") is None or shutil.which("xdotool") is None,
                    reason="Xvfb and xdotool drive the window: bash scripts/setup.sh --dev installs them")
def test_keyboard_session_under_xvfb(tmp_path):
    """A person's session: key presses reach the window, the screenshot shows scene + overlays, the
    recorded episode holds the keys' twists, finite executed twists and mode labels."""
    xvfb, display = _start_xvfb()
    record, shot = tmp_path / "session", tmp_path / "teleop.png"
    env = dict(os.environ, DISPLAY=display, SDL_VIDEODRIVER="x11", SDL_AUDIODRIVER="dummy")
    proc = subprocess.Popen([RTV3, "teleop", "--method", "rtv3", "--input", "keyboard", "--record", str(record),
                             "--scene-seed", "3", "--screenshot", str(shot)], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in proc.stdout:  # the trial starts once the scene is loaded and shown
            lines.append(line)
            if "started" in line:
                break
        assert lines and "started" in lines[-1], "".join(lines)[-3000:]
        window = _xdotool(display, "search", "--sync", "--class", "rtv3").split()[0]
        _xdotool(display, "windowfocus", "--sync", window)
        for key, seconds in (("w", 1.0), ("q", 1.0)):  # short: the trial must still be running at F12
            _xdotool(display, "keydown", key)
            time.sleep(seconds)
            _xdotool(display, "keyup", key)
            time.sleep(0.5)
        _xdotool(display, "key", "F12")  # pygame saves the window to --screenshot
        time.sleep(1.5)
        _xdotool(display, "key", "Escape")
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        xvfb.terminate()
        xvfb.wait(timeout=10)
    assert proc.returncode == 0, output[-3000:]
    assert shot.exists(), f"no screenshot written:\n{output[-2000:]}"

    import pygame

    image = pygame.surfarray.array3d(pygame.image.load(str(shot))).swapaxes(0, 1)  # (H, W, 3)
    scene, panel = image[:, :512], image[:, 512:]
    assert len(np.unique(scene.reshape(-1, 3), axis=0)) > 200, "the scene view looks empty"
    assert (panel.max(-1) > 200).sum() > 2000, "the overlay panel has no text"

    assert (record / "data").exists(), f"nothing recorded:\n{output[-3000:]}"
    frames = _frames(record)
    user = np.stack(frames[USER_TWIST].to_numpy())
    mapping = KeyboardMapping()
    w, q = mapping.twist({"w"}).numpy(), mapping.twist({"q"}).numpy()
    moving = user[np.abs(user).sum(1) > 0]
    # both keys reached the session (a loaded machine runs the 20 Hz loop slower: a 1 s press may be 1-2 frames)
    assert len(moving) >= 2, "the key presses did not reach the session"
    assert all(np.allclose(row, w, atol=1e-6) or np.allclose(row, q, atol=1e-6) for row in moving), moving[:5]
    assert np.isclose(moving, w, atol=1e-6).all(1).any() and np.isclose(moving, q, atol=1e-6).all(1).any()
    for key in (features.ACTION, "commanded_twist"):
        assert np.isfinite(np.stack(frames[key].to_numpy())).all()
    modes = {ASSIST_MODES[int(np.ravel(m)[0])] for m in frames["assist_mode"]}
    assert modes & {"shared", "autonomous", "user_only"}, modes
    assert {OUTCOMES[int(np.ravel(o)[0])] for o in frames["trial_outcome"]} == {"aborted"}
    assert (record / "sessions.csv").read_text().count("aborted") == 1


class ButtonScript:
    """An input that holds still and presses approach, grasp, lift in turn (what a person does at the pre-grasp)."""

    name = "buttons"

    def reset(self, env, actions=None) -> None:
        self.actions, self.todo = actions, ["approach", "grasp", "lift"]

    def poll(self, tcp_pose, events):
        from rtv3_maniskill.teleop.inputs import UserInput

        buttons = [self.todo.pop(0)] if self.todo and not self.actions.scripted else []
        return UserInput(torch.zeros(6, dtype=torch.float64), torch.zeros(6, dtype=torch.float64), buttons)


def test_grasp_buttons_lift_the_target_and_a_miss_fails(tmp_path):
    """From the target's pre-grasp (IK), Y-A-X lift the target: success, recorded; from 6 cm further back
    the gripper closes on air: the trial fails."""
    from rtv3_maniskill import se3
    from rtv3_maniskill.robot.planner import PandaPlanner
    from rtv3_maniskill.teleop.grasp_trial import TrialConfig
    from rtv3_maniskill.teleop.session import SessionConfig, TeleopSession

    config = SessionConfig(method="direct", input="simulated:ideal", scene_seed=2, headless=True,
                           record=tmp_path / "session", trial_config=TrialConfig(timeout_s=8.0))
    session = TeleopSession(config)
    session.input, session.simulated = ButtonScript(), True
    try:
        session.env.reset(seed=2)
        planner = PandaPlanner(session.env.base.layouts[0])
        pregrasp = session.env.user_goal()
        config.init_qpos = planner.solve_ik(pregrasp.numpy())
        assert config.init_qpos is not None
        hit = session.run_trial(0)
        config.init_qpos = planner.solve_ik(se3.translate_along_z(pregrasp, -0.06).numpy())
        assert config.init_qpos is not None
        miss = session.run_trial(1)
    finally:
        session.close()
    assert hit.outcome == "success", hit
    assert miss.outcome != "success", miss
    frames = _frames(tmp_path / "session")
    buttons = np.stack(frames[frames["episode_index"] == 0]["button_events"].to_numpy())
    assert buttons.sum(0).tolist() == [1, 0, 1, 1]  # grasp, release, approach, lift
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset("local/session", root=tmp_path / "session")
    assert dataset.meta.total_episodes == 2
    first = dataset[0]
    assert first[features.STATE_HISTORY].shape == (features.HISTORY_STEPS * features.STATE_DIM,)
    assert first["class_weights"].shape == (64,)


def _session_after_its_first_trial(cmd: list[str], folder: Path) -> tuple[subprocess.Popen, Path]:
    """``rtv3 CMD`` started as a process, returned once its first trial is in ``sessions.csv``."""
    log = open(folder.parent / f"{folder.name}.log", "w")  # a file, not a pipe: a full pipe would stall the run
    proc = subprocess.Popen([RTV3, *cmd], stdout=log, stderr=subprocess.STDOUT, text=True,
                            env=dict(os.environ, PYTHONWARNINGS="ignore"))
    log.close()
    sessions = folder / "sessions.csv"
    deadline = time.time() + 300
    while time.time() < deadline and not (sessions.is_file() and len(sessions.read_text().splitlines()) >= 2):
        time.sleep(0.05)
    return proc, sessions


def test_a_killed_session_keeps_its_finished_trials_and_resumes(tmp_path):
    """SIGKILL during trial 2: trial 1 loads with LeRobot, --resume records trials 2 and 3, study analyze reads all."""
    import signal

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.cli import main
    from rtv3_maniskill.features import REPO_ID

    folder = tmp_path / "P01_direct"
    cmd = ["teleop", "--method", "direct", "--input", "simulated:ideal", "--headless", "--trials", "3",
           "--timeout", "6", "--participant", "P01", "--record", str(folder)]
    proc, sessions = _session_after_its_first_trial(cmd, folder)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert len(sessions.read_text().splitlines()) == 2, "killed during trial 2: one finished trial"
    dataset = LeRobotDataset(REPO_ID, root=folder)
    assert dataset.meta.total_episodes == 1 and dataset.num_frames == len(_frames(folder)) > 0
    assert main([*cmd, "--resume"]) == 0
    rows = pd.read_csv(sessions)
    assert list(rows["trial"]) == [0, 1, 2] and list(rows["episode_index"]) == [0, 1, 2]
    assert list(rows["scene_seed"]) == [0, 1, 2]  # the same schedule, continued
    assert LeRobotDataset(REPO_ID, root=folder).meta.total_episodes == 3
    assert main(["study", "analyze", str(folder), "--output", str(tmp_path / "analysis")]) == 0
    assert len(pd.read_csv(tmp_path / "analysis" / "trials.csv")) == 3
    with pytest.raises(SystemExit, match="recorded with participant='P01', not 'P02'"):
        main([*cmd[:-4], "--participant", "P02", "--record", str(folder), "--resume"])


def test_ctrl_c_ends_a_session_cleanly_and_keeps_its_trials(tmp_path):
    import signal

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.features import REPO_ID

    folder = tmp_path / "P02_direct"
    proc, sessions = _session_after_its_first_trial(
        ["teleop", "--method", "direct", "--input", "simulated:ideal", "--headless", "--trials", "3", "--timeout", "6",
         "--record", str(folder)], folder)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=120)
    output = (tmp_path / "P02_direct.log").read_text()
    assert proc.returncode == 130, output[-2000:]
    assert "Traceback" not in output and "interrupted" in output
    assert LeRobotDataset(REPO_ID, root=folder).meta.total_episodes == len(pd.read_csv(sessions)) >= 1


def test_a_session_behind_the_safety_filter_is_recorded_and_analysed_under_its_name(tmp_path):
    """`teleop --safety-filter neoss`: the arm runs behind NeoSS; sessions.csv and the study name it rtv3+neoss."""
    from rtv3_maniskill.cli import main

    folder = tmp_path / "P01_rtv3_neoss"
    assert main(["teleop", "--method", "rtv3", "--safety-filter", "neoss", "--input", "simulated:noisy", "--headless",
                 "--timeout", "3", "--participant", "P01", "--record", str(folder)]) == 0
    rows = pd.read_csv(folder / "sessions.csv")
    assert list(rows["method"]) == ["rtv3+neoss"]
    assert main(["study", "analyze", str(folder), "--output", str(tmp_path / "analysis")]) == 0
    assert set(pd.read_csv(tmp_path / "analysis" / "trials.csv")["method"]) == {"rtv3+neoss"}
