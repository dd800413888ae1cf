"""LeRobot's own dataset tools (``lerobot.datasets.dataset_tools``, ``lerobot-edit-dataset``)
on an `rtv3 generate` dataset: delete_episodes, split, merge and modify_tasks; and `rtv3 merge`.

LeRobot 0.4.4 copies data through pandas, which cannot handle 2-D (``Array2D``) columns; the
dataset stores its 2-D features flat (``features.STORED_FLAT``) so that these tools work.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from rtv3_maniskill import features
from rtv3_maniskill.cli import main
from rtv3_maniskill.features import REPO_ID

ARGS = ["--num-points", "64", "--max-grasps", "16", "--context", "mesh", "--scene-type", "packed"]


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tools") / "ds"
    # seed 0: 6 of the 6 targets succeed (>= 3 episodes for split + merge)
    assert main(["generate", "--num-scenes", "2", "--grasps-per-scene", "3", "--output", str(root), *ARGS]) == 0
    return root


def _episodes(ds) -> list[tuple[int, int, str]]:
    """(scene seed, target grasp, task) per episode, from the frames."""
    hf = ds.hf_dataset.with_format("numpy")
    out = {}
    for row in range(len(hf)):
        item = ds[row]
        out.setdefault(int(item["episode_index"]),
                       (int(item["scene_seed"]), int(item[features.TARGET_GRASP]), item["task"]))
    return [out[k] for k in sorted(out)]


def _check_loads(repo_id: str, root: Path, expected: list[tuple[int, int]], num_points: int = 64, max_grasps: int = 16):
    """The dataset at ``root`` loads with LeRobotDataset, holds ``expected`` (scene, grasp) episodes
    in that order, and its stored features read back in the documented layout."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=root)
    assert ds.num_episodes == len(expected)
    assert [e[:2] for e in _episodes(ds)] == expected
    assert list(np.unique(np.asarray(ds.hf_dataset["episode_index"]).reshape(-1))) == list(range(len(expected)))
    item = ds[len(ds) - 1]
    assert features.unflatten(features.POINT_CLOUD, item[features.POINT_CLOUD]).shape == (num_points, 6)
    assert features.unflatten(features.GRASPS, item[features.GRASPS]).shape == (max_grasps, features.GRASP_DIM)
    history = features.unflatten(features.STATE_HISTORY, item[features.STATE_HISTORY])
    assert torch.equal(history[-1], item[features.STATE])
    return ds


@pytest.mark.sim
def test_delete_split_merge_modify_tasks_with_lerobot_dataset_tools(generated, tmp_path):
    from lerobot.datasets.dataset_tools import delete_episodes, merge_datasets, modify_tasks, split_dataset
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    source = LeRobotDataset(REPO_ID, root=generated)
    episodes = [e[:2] for e in _episodes(source)]
    assert len(episodes) >= 3

    # delete_episodes: episode 0 gone, the others renumbered, frames intact
    deleted = delete_episodes(source, [0], output_dir=tmp_path / "deleted", repo_id="local/deleted")
    kept = _check_loads("local/deleted", tmp_path / "deleted", episodes[1:])
    first_kept = int(np.flatnonzero(np.asarray(source.hf_dataset["episode_index"]).reshape(-1) == 1)[0])
    for key in (features.POINT_CLOUD, features.GRASPS, features.STATE_HISTORY, features.ACTION):
        assert torch.equal(kept[0][key], source[first_kept][key])
    assert deleted.meta.total_frames == len(source) - source.meta.episodes[0]["length"]

    # split: by episode lists
    parts = split_dataset(source, {"train": list(range(len(episodes) - 1)), "val": [len(episodes) - 1]},
                          output_dir=tmp_path / "split")
    train = _check_loads(parts["train"].repo_id, tmp_path / "split" / "train", episodes[:-1])
    val = _check_loads(parts["val"].repo_id, tmp_path / "split" / "val", episodes[-1:])
    assert len(train) + len(val) == len(source)

    # merge: the two splits back into one dataset, in order
    merge_datasets([train, val], output_repo_id="local/merged", output_dir=tmp_path / "merged")
    merged = _check_loads("local/merged", tmp_path / "merged", episodes)
    assert len(merged) == len(source)

    # modify_tasks (in place): on a copy
    shutil.copytree(generated, tmp_path / "retasked", ignore=shutil.ignore_patterns("rtv3_staging"))
    modify_tasks(LeRobotDataset(REPO_ID, root=tmp_path / "retasked"), new_task="grasp something",
                 episode_tasks={1: "grasp that"})
    retasked = _check_loads(REPO_ID, tmp_path / "retasked", episodes)
    tasks = [e[2] for e in _episodes(retasked)]
    assert tasks[1] == "grasp that" and set(tasks[:1] + tasks[2:]) == {"grasp something"}


@pytest.mark.sim
def test_lerobot_edit_dataset_cli_delete_episodes(generated, tmp_path):
    """The CLI writes to ``--root / --new_repo_id``; a rerun into the same folder is LeRobot's
    FileExistsError (a folder left by a failed run must be removed first)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path / "ds"
    shutil.copytree(generated, root)
    episodes = [e[:2] for e in _episodes(LeRobotDataset(REPO_ID, root=root))]
    cli = Path(sys.executable).parent / "lerobot-edit-dataset"
    cmd = [str(cli), f"--repo_id={REPO_ID}", f"--root={root}", "--operation.type=delete_episodes",
           "--operation.episode_indices=[0, 2]", "--new_repo_id=local/fewer"]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    _check_loads("local/fewer", root / "local" / "fewer", [episodes[1], *episodes[3:]])


@pytest.mark.sim
def test_rtv3_merge_of_a_merged_dataset_keeps_every_episode(generated, tmp_path, capsys):
    """A merge whose episode metadata spilled into a second file (LeRobot 0.4.4 labels both files 0)
    merges again with every episode, in order, through ``rtv3 merge``."""
    import pyarrow.parquet as pq
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.datagen.merge import repair_episode_file_labels

    spilled = tmp_path / "spilled"
    shutil.copytree(generated, spilled, ignore=shutil.ignore_patterns("rtv3_staging"))
    meta_dir = spilled / "meta" / "episodes" / "chunk-000"
    table = pq.read_table(meta_dir / "file-000.parquet")
    half = table.num_rows // 2
    pq.write_table(table.slice(0, half), meta_dir / "file-000.parquet")
    pq.write_table(table.slice(half), meta_dir / "file-001.parquet")  # labelled file 0, as LeRobot leaves it
    episodes = [e[:2] for e in _episodes(LeRobotDataset(REPO_ID, root=generated))]
    _check_loads(REPO_ID, spilled, episodes)  # the spilled dataset itself still loads whole

    assert main(["merge", str(spilled), str(generated), "--output", str(tmp_path / "again")]) == 0
    assert f"{2 * len(episodes)} episodes" in capsys.readouterr().out
    assert repair_episode_file_labels(spilled) == 0  # merge mended its source first
    _check_loads(REPO_ID, tmp_path / "again", episodes + episodes)


@pytest.mark.sim
@pytest.mark.parametrize("case, message", [
    ("missing", "error: no such dataset folder: {tmp}/nowhere"),
    ("not_a_dataset", "error: not a LeRobot dataset (no meta/info.json): {tmp}/empty"),
    ("output_exists", "error: {tmp}/out exists; remove it or choose another folder"),
])
def test_rtv3_merge_refuses_bad_folders_with_one_error_line(generated, tmp_path, case, message):
    (tmp_path / "empty").mkdir()
    (tmp_path / "out").mkdir()
    sources = {"missing": [tmp_path / "nowhere", generated], "not_a_dataset": [tmp_path / "empty"],
               "output_exists": [generated]}[case]
    output = tmp_path / ("out" if case == "output_exists" else "merged")
    with pytest.raises(SystemExit) as exit_info:
        main(["merge", *map(str, sources), "--output", str(output)])
    assert exit_info.value.code == message.format(tmp=tmp_path)
    assert not (tmp_path / "merged").exists()


@pytest.mark.sim
def test_rtv3_merge_adds_the_scene_summary_to_a_dataset_written_without_it(generated, tmp_path):
    """Datasets from before the scene summary keep working: `rtv3 merge` derives
    observation.environment_state from their point clouds and grasps, with its statistics."""
    from lerobot.datasets.dataset_tools import remove_feature
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    old = tmp_path / "old"
    remove_feature(LeRobotDataset(REPO_ID, root=generated), features.ENV_STATE, output_dir=old, repo_id=REPO_ID)
    assert features.ENV_STATE not in LeRobotDataset(REPO_ID, root=old).meta.features
    assert main(["merge", str(old), "--output", str(tmp_path / "new")]) == 0
    new, original = LeRobotDataset(REPO_ID, root=tmp_path / "new"), LeRobotDataset(REPO_ID, root=generated)
    assert new.num_frames == original.num_frames
    for row in (0, len(new) - 1):
        assert torch.allclose(new[row][features.ENV_STATE], original[row][features.ENV_STATE], atol=1e-6)
    stats = new.meta.stats[features.ENV_STATE]
    assert stats["max"].shape == (features.scene_summary_dim(16),)
    assert not (tmp_path / ".new.with-summary").exists()
