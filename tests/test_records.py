"""The record store every resumable run uses: torn rows, settings guard, numbering, targets."""

from __future__ import annotations

import logging
import subprocess
import sys

import pytest

from rtv3_maniskill.records import (
    FolderBusy,
    RecordStore,
    SettingsMismatch,
    claim_folder,
    scene_seeds,
    select_targets,
)

FIELDS = ("scene_seed", "grasp_index", "outcome", "steps")
KEY = ("scene_seed", "grasp_index")


def test_torn_last_row_is_not_a_result_and_is_rerun(tmp_path):
    path = tmp_path / "results.csv"
    with RecordStore(path, FIELDS, KEY, settings={"seed": 9}) as store:
        store.append(dict(scene_seed=900000, grasp_index=0, outcome="success", steps=40))
    with open(path, "a") as f:  # a killed process wrote half a row
        f.write("900000,1,succ")
    store = RecordStore(path, FIELDS, KEY, settings={"seed": 9})
    assert len(store) == 1
    assert (900000, 0) in store and (900000, 1) not in store
    store.append(dict(scene_seed=900000, grasp_index=1, outcome="timeout", steps=150))
    store.close()
    rows = RecordStore.read(path, FIELDS)
    assert [r["outcome"] for r in rows] == ["success", "timeout"]
    assert path.read_text().count("\n") == 3  # header + two whole rows, nothing glued


def test_other_settings_are_refused_once_a_record_exists(tmp_path):
    path = tmp_path / "results.csv"
    with RecordStore(path, FIELDS, KEY, settings={"seed": 9, "users": ["noisy"]}) as store:
        store.append(dict(scene_seed=1, grasp_index=2, outcome="success", steps=3))
    with pytest.raises(SettingsMismatch, match="seed: 9 -> 10"):
        RecordStore(path, FIELDS, KEY, settings={"seed": 10, "users": ["noisy"]})
    RecordStore(path, FIELDS, KEY, settings={"seed": 9, "users": ("noisy",)}).close()  # tuples == lists


def test_a_run_that_failed_before_its_first_record_does_not_block_the_fix(tmp_path):
    path = tmp_path / "attempts.csv"
    RecordStore(path, FIELDS, KEY, settings={"objects": "/nonexistent"}).close()
    with RecordStore(path, FIELDS, KEY, settings={"objects": "procedural"}) as store:
        store.append(dict(scene_seed=1, grasp_index=0, outcome="success", steps=1))
    assert '"procedural"' in store.settings_path.read_text()


def test_a_foreign_file_is_refused_with_its_name(tmp_path):
    path = tmp_path / "results.csv"
    path.write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="results.csv has the columns"):
        RecordStore(path, FIELDS, KEY)


def test_scene_numbering_and_seeded_targets():
    assert scene_seeds(9, 3) == [900000, 900001, 900002]
    valid = [5, 1, 9, 3, 7]
    assert select_targets(valid, None, 9, 900000, salt=17) == [1, 3, 5, 7, 9]
    a = select_targets(valid, 2, 9, 900000, salt=17)
    assert a == select_targets(valid, 2, 9, 900000, salt=17) and len(a) == 2 and set(a) <= set(valid)
    picks = {tuple(select_targets(valid, 2, 9, s, salt=17)) for s in range(900000, 900020)}
    assert len(picks) > 1  # the subset depends on the scene
    with pytest.raises(ValueError, match=">= 1"):
        select_targets(valid, 0, 9, 900000, salt=17)


_HOLD = """
import sys, time
from rtv3_maniskill.records import RecordStore
store = RecordStore(sys.argv[1], ("k", "v"), ("k",), settings={"a": 1})
print("holding", flush=True)
time.sleep(60)
"""


def _hold_in_another_process(path):
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(path)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "holding"
    return proc


def test_a_second_writer_of_a_folder_is_stopped_with_the_holder_named_and_the_lock_dies_with_it(tmp_path):
    path = tmp_path / "run" / "results.csv"
    holder = _hold_in_another_process(path)
    try:
        with pytest.raises(FolderBusy, match=rf"{tmp_path / 'run'} is being written by pid {holder.pid}"):
            RecordStore(path, ("k", "v"), ("k",), settings={"a": 1})
        with pytest.raises(FolderBusy):  # a command claims the folder before it builds anything
            claim_folder(tmp_path / "run")
        assert RecordStore.read(path, ("k", "v")) == []  # readers are not locked out
    finally:
        holder.kill()  # SIGKILL: the kernel drops the lock with the process
        holder.wait()
    with RecordStore(path, ("k", "v"), ("k",), settings={"a": 1}) as store:
        store.append({"k": 1, "v": 2})
        with RecordStore(tmp_path / "run" / "other.csv", ("k",), ("k",)):  # claims nest in one process
            pass
    assert RecordStore.read(path, ("k", "v")) == [{"k": "1", "v": "2"}]


def test_a_key_written_twice_counts_once_and_is_named(tmp_path, caplog):
    path = tmp_path / "results.csv"
    path.write_text("k,v\n1,a\n2,b\n1,a\n")
    with caplog.at_level(logging.WARNING, logger="rtv3_maniskill.records"):
        rows = RecordStore.read(path, ("k", "v"), key=("k",))
    assert rows == [{"k": "1", "v": "a"}, {"k": "2", "v": "b"}]
    assert len(caplog.records) == 1 and "1 record(s) more than once (k: 1)" in caplog.records[0].getMessage()
    with RecordStore(path, ("k", "v"), ("k",)) as store:
        assert len(store) == 2
