"""What a newcomer meets first: cheap imports, and a LeRobot plugin found from any folder."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.sim  # every test here runs the simulator

REPO = Path(__file__).resolve().parents[1]


def _python(code: str, cwd: Path = REPO, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *flags, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_pure_modules_load_no_simulator():
    code = (
        "import sys\n"
        "import rtv3_maniskill, rtv3_maniskill.se3, rtv3_maniskill.features, rtv3_maniskill.shared_control\n"
        "import rtv3_maniskill.records, rtv3_maniskill.cli\n"
        "rtv3_maniskill.cli.build_parser()\n"
        "print(sorted(m for m in ('sapien', 'mani_skill', 'lerobot') if m in sys.modules))\n"
    )
    run = _python(code)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"
    timed = _python("import rtv3_maniskill.se3", REPO, "-X", "importtime")
    assert "sapien" not in timed.stderr and "mani_skill" not in timed.stderr


def test_task_is_made_after_the_documented_import():
    # ``import rtv3_maniskill`` registers the task lazily; gym.make loads ManiSkill and applies its
    # 150-step limit.
    code = (
        "import gymnasium as gym, torch, rtv3_maniskill\n"
        "env = gym.make('GraspClutter-v1', obs_mode='state_dict', control_mode='pd_ee_twist', num_points=64)\n"
        "obs, _ = env.reset(seed=1)\n"
        "ends = [bool(env.step(torch.zeros(1, 7))[3][0]) for _ in range(150)]\n"
        "print(type(env.unwrapped).__name__, ends.index(True) + 1, tuple(obs['extra']['tcp_pose'].shape))\n"
    )
    run = _python(code)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split()[-4:] == ["GraspClutterEnv", "150", "(1,", "7)"]


def test_lerobot_finds_the_policy_from_the_repository_root():
    # Python started in the repository root puts it first on sys.path: no folder there may
    # shadow the installed plugin package.
    code = (
        "import sys\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()\n"
        "from lerobot.policies.factory import get_policy_class, make_policy_config\n"
        "print(get_policy_class('rtv3').__name__, type(make_policy_config('rtv3')).__name__)\n"
        "print('sapien' in sys.modules)\n"
    )
    run = _python(code, REPO)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["RTV3Policy", "RTV3Config", "False"]
