"""The scene pool: local processes and a real 2-CPU Ray cluster give the same records, and a failing
worker stops the run with its error."""

from __future__ import annotations

import csv
import time

import numpy as np
import pytest

from rtv3_maniskill.scene_pool import SceneWorkerError, run_scenes

pytestmark = pytest.mark.sim  # every test here runs the simulator

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def ray_cluster():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.parametrize("workers", [1, 2])
def test_local_results_and_a_failing_job_stops_the_run(workers):
    # builtins as init and job: importable in every worker. State int("7") = 7; job divmod(7, item).
    assert sorted(run_scenes(int, "7", divmod, [1, 2, 3], workers=workers)) == [(2, 1), (3, 1), (7, 0)]
    with pytest.raises(SceneWorkerError, match="ZeroDivisionError"):
        list(run_scenes(int, "7", divmod, [1, 0, 2], workers=workers))


def test_a_worker_that_fails_to_start_stops_the_local_run_at_once():
    start = time.monotonic()
    with pytest.raises(SceneWorkerError, match="failed to start: ValueError: invalid literal for int"):
        list(run_scenes(int, "seven", divmod, list(range(20)), workers=2))
    assert time.monotonic() - start < 60


def test_ray_results_and_errors(ray_cluster):
    assert sorted(run_scenes(int, "7", divmod, [1, 2, 3], workers=2, executor="ray")) == [(2, 1), (3, 1), (7, 0)]
    with pytest.raises(SceneWorkerError, match="ZeroDivisionError"):
        list(run_scenes(int, "7", divmod, [1, 0], workers=2, executor="ray"))
    with pytest.raises(SceneWorkerError, match="failed to start: ValueError"):
        list(run_scenes(int, "seven", divmod, [1, 2], workers=2, executor="ray"))
    with pytest.raises(ValueError, match="unknown executor 'dask'"):
        run_scenes(int, "7", divmod, [1], executor="dask")


def _trials(folder):
    with open(folder / "results.csv") as f:
        return {(r["scene_seed"], r["grasp_index"], r["user"], r["method"]): (r["outcome"], r["steps"])
                for r in csv.DictReader(f)}


def test_benchmark_under_ray_gives_the_local_results_and_either_resumes_the_other(ray_cluster, tmp_path):
    from rtv3_maniskill.cli import main

    common = ["benchmark-shared", "--scenes", "2", "--goals-per-scene", "2", "--users", "noisy",
              "--methods", "direct,rtv3", "--no-progress", "--workers", "2"]
    assert main([*common, "--output", str(tmp_path / "local")]) == 0
    assert main([*common, "--output", str(tmp_path / "ray"), "--executor", "ray"]) == 0
    local, under_ray = _trials(tmp_path / "local"), _trials(tmp_path / "ray")
    assert len(local) == 8 and under_ray == local
    # A run stopped after its first scene under Ray is finished by local processes.
    partial = [*common, "--output", str(tmp_path / "resumed")]
    partial[partial.index("--scenes") + 1] = "1"
    assert main([*partial, "--executor", "ray"]) == 0
    assert len(_trials(tmp_path / "resumed")) == 4
    assert main([*common, "--output", str(tmp_path / "resumed")]) == 0
    assert _trials(tmp_path / "resumed") == local


def _episodes(root):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset("local/test", root=root)
    frame = dataset.hf_dataset.with_format("numpy")
    return (dataset.meta.total_episodes, float(np.asarray(frame["observation.state"]).sum()),
            float(np.asarray(frame["action"]).sum()))


def test_generate_under_ray_gives_the_local_episodes(ray_cluster, tmp_path):
    from rtv3_maniskill.cli import main

    common = ["generate", "--num-scenes", "2", "--grasps-per-scene", "2", "--num-points", "256", "--seed", "3",
              "--context", "mesh"]
    assert main([*common, "--output", str(tmp_path / "local"), "--workers", "2"]) == 0
    assert main([*common, "--output", str(tmp_path / "ray"), "--workers", "2", "--executor", "ray"]) == 0
    local, under_ray = _episodes(tmp_path / "local"), _episodes(tmp_path / "ray")
    assert local[0] >= 2 and under_ray[0] == local[0]
    assert under_ray[1:] == pytest.approx(local[1:])
