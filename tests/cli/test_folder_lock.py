"""One writer per record folder: every command that writes one stops at once while another process holds it."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from rtv3_maniskill.cli import main

_HOLD = """
import sys, time
from rtv3_maniskill.records import claim_folder
claim_folder(sys.argv[1])
print("holding", flush=True)
time.sleep(120)
"""

COMMANDS = {
    "generate": ["generate", "--num-scenes", "1"],
    "dagger": ["dagger", "--num-scenes", "1"],
    "evaluate planning": ["evaluate", "planning", "--scenes", "1"],
    "benchmark-shared": ["benchmark-shared", "--scenes", "1", "--goals-per-scene", "1", "--users", "noisy",
                         "--methods", "direct"],
    "teleop --resume": ["teleop", "--input", "simulated:noisy", "--headless", "--resume", "--record"],
}


@pytest.fixture(scope="module")
def held_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("held") / "run"
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "holding"
    yield folder, proc.pid
    proc.kill()
    proc.wait()


@pytest.mark.parametrize("command", COMMANDS)
def test_a_second_writer_stops_at_once_with_one_line(command, held_folder, capsys):
    folder, pid = held_folder
    argv = COMMANDS[command] + ([str(folder)] if command.startswith("teleop") else ["--output", str(folder)])
    start = time.perf_counter()
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 1
    assert time.perf_counter() - start < 30
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{folder} is being written by pid {pid}" in err[0], err
    assert sorted(p.name for p in folder.iterdir()) == [".rtv3-writer.lock"]  # nothing was built or written
