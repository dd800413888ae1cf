"""Resumable run records: every long run (dataset generation, benchmarks) keeps its results here.

A run folder holds one append-only CSV per kind of record (one row per finished unit of work:
an attempted demonstration, a planning trial, a shared-control trial) and a JSON file with the
run's settings. A rerun with the same settings skips the finished rows; a rerun with other
settings is refused, but only once the folder holds a record (a run that failed before its
first record never blocks the corrected rerun).

Every row is flushed and fsync'd as it is written. A row torn by a killed process (the file
does not end with a newline) is cut off when the store is opened, so it is neither counted nor
glued to the next row. This module also owns the scene numbering and the seeded choice of
targets that every run shares, so that the same seed means the same scenes everywhere.

One process writes a run folder at a time: :func:`claim_folder` takes an exclusive ``flock`` on
``<folder>/.rtv3-writer.lock`` (the kernel drops it when the process ends, SIGKILL included) and a
second writer gets :class:`FolderBusy`, naming the holding process. Every writing
:class:`RecordStore` claims its folder; the commands claim theirs before they build anything.
Readers (:meth:`RecordStore.read`) take no lock. A store written before the lock existed may
hold a key twice: the rows keep the first, and one log line names the repeated keys.
"""

from __future__ import annotations

import csv
import fcntl
import io
import json
import logging
import os
import socket
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

LOCK_FILE = ".rtv3-writer.lock"
"""The lock file a writer holds in its run folder."""

SCENE_SEED_STRIDE = 100000
"""Scene ``i`` of a run with seed ``s`` has scene seed ``s * SCENE_SEED_STRIDE + i``."""


def scene_seeds(seed: int, count: int) -> list[int]:
    """The scene seeds ``seed * 100000 + i`` for ``i < count``."""
    if count < 0:
        raise ValueError(f"the number of scenes must be >= 0, got {count}")
    return [int(seed) * SCENE_SEED_STRIDE + i for i in range(count)]


def select_targets(valid: Iterable[int], cap: int | None, seed: int, scene_seed: int, salt: int) -> list[int]:
    """All ``valid`` indices (sorted), or a seeded random subset of ``cap`` of them (sorted).

    The subset depends only on ``(seed, scene_seed, salt)``: each kind of run has its own
    ``salt``, so a planning run and a shared-control run with the same seed pick independently.
    """
    valid = sorted(int(v) for v in valid)
    if cap is not None and cap < 1:
        raise ValueError(f"the number of targets per scene must be >= 1 (or None for all), got {cap}")
    if cap is None or cap >= len(valid):
        return valid
    rng = np.random.default_rng([int(seed), int(scene_seed), int(salt)])
    return sorted(int(i) for i in rng.choice(valid, size=cap, replace=False))


class SettingsMismatch(ValueError):
    """A run folder holds records made with other settings (the message names them)."""


class FolderBusy(RuntimeError):
    """Another process is writing this run folder (the message names the folder and the process)."""


class FolderClaim:
    """This process's exclusive hold on a run folder (see :func:`claim_folder`); :meth:`release` gives it up."""

    _held: dict[Path, list] = {}  # folder -> [file object holding the flock, claims in this process]

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._released = False

    def release(self) -> None:
        """Give up this claim; the lock goes when the process's last claim on the folder does (idempotent)."""
        if self._released:
            return
        self._released = True
        entry = FolderClaim._held.get(self.folder)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] == 0:
            del FolderClaim._held[self.folder]
            entry[0].close()  # closing the descriptor drops the flock

    def __enter__(self) -> FolderClaim:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


def claim_folder(folder: str | Path) -> FolderClaim:
    """Claim ``folder`` (created if missing) for writing by this process.

    Claims nest within a process (every store of a run claims the run's folder); another process
    holding the folder raises :class:`FolderBusy` at once, naming the folder and that process.
    """
    folder = Path(folder).expanduser().absolute()
    entry = FolderClaim._held.get(folder)
    if entry is None:
        folder.mkdir(parents=True, exist_ok=True)
        handle = open(folder / LOCK_FILE, "a+")
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            raise FolderBusy(f"{folder} is being written by {holder}; wait for that run to end (or stop it) "
                             "before you resume here, or write to another folder") from None
        handle.seek(0)
        handle.truncate()
        command = " ".join([Path(sys.argv[0]).name, *sys.argv[1:3]]) if sys.argv and sys.argv[0] else "python"
        handle.write(f"pid {os.getpid()} on {socket.gethostname()} (`{command}`, since "
                     f"{time.strftime('%Y-%m-%d %H:%M:%S')})\n")
        handle.flush()
        entry = FolderClaim._held[folder] = [handle, 0]
    entry[1] += 1
    return FolderClaim(folder)


def first_of_each_key(rows: list[dict[str, str]], key: Sequence[str], source: str | Path) -> list[dict[str, str]]:
    """``rows`` with each ``key`` once (its first row); logs one line naming the keys found more than once."""
    seen: dict[tuple[str, ...], int] = {}
    kept = []
    for row in rows:
        k = tuple(str(row[c]) for c in key)
        seen[k] = seen.get(k, 0) + 1
        if seen[k] == 1:
            kept.append(row)
    repeated = [k for k, n in seen.items() if n > 1]
    if repeated:
        names = ", ".join("/".join(k) for k in repeated[:5]) + (f" and {len(repeated) - 5} more" if len(repeated) > 5
                                                              else "")
        log.warning("%s holds %d record(s) more than once (%s: %s), counted once each: written by two runs at a "
                    "time before run folders were locked", source, len(repeated), "/".join(key), names)
    return kept


def _fsync_write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temporary file, fsync, rename)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class RecordStore:
    """An append-only CSV of finished records, keyed, with the run's settings beside it.

    Args:
        path: the CSV file (created with a header when missing).
        fields: its columns, in order. An existing file with other columns is refused.
        key: the columns that identify a record (e.g. ``("scene_seed", "grasp_index")``).
        settings: the run's settings (JSON-serialisable). When the store already holds a
            record, they must equal those saved with it, else :class:`SettingsMismatch`.
            ``None`` = no guard (read-only use, merged folders).
        settings_path: where they are kept; default ``<path stem>.settings.json`` beside ``path``.
        is_complete: optional check of a parsed row; rows failing it are ignored as torn.
    """

    def __init__(self, path: str | Path, fields: Sequence[str], key: Sequence[str],
                 settings: dict[str, Any] | None = None, settings_path: str | Path | None = None,
                 is_complete: Callable[[dict[str, str]], bool] | None = None) -> None:
        self.path = Path(path)
        self.fields = tuple(fields)
        self.key_fields = tuple(key)
        missing = [k for k in self.key_fields if k not in self.fields]
        if missing:
            raise ValueError(f"key columns {missing} are not among the fields {list(self.fields)}")
        self.settings_path = Path(settings_path) if settings_path is not None else self.path.with_name(
            self.path.stem + ".settings.json")
        self._is_complete = is_complete
        self._claim = claim_folder(self.settings_path.parent)  # FolderBusy while another process writes it
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._cut_torn_tail()
            self.rows: list[dict[str, str]] = (self.read(self.path, self.fields, is_complete, key=self.key_fields)
                                               if self.path.exists() else [])
            self._by_key = {self.key(row): row for row in self.rows}
            if settings is not None:
                self._guard_settings(settings)
        except BaseException:
            self._claim.release()
            raise
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._file = open(self.path, "a", newline="")
        self._writer = csv.DictWriter(self._file, self.fields)
        if new:
            self._writer.writeheader()
            self._flush()

    # ------------------------------------------------------------------ reading

    @staticmethod
    def read(path: str | Path, fields: Sequence[str],
             is_complete: Callable[[dict[str, str]], bool] | None = None,
             key: Sequence[str] | None = None) -> list[dict[str, str]]:
        """The complete rows of a record file (strings). A torn row (missing or extra columns,
        no newline at the end of the file, or failing ``is_complete``) is skipped. With ``key``,
        a key found more than once keeps its first row (:func:`first_of_each_key`).

        Raises:
            FileNotFoundError: no file at ``path``.
            ValueError: the header is not ``fields`` (the message names the file and both).
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no record file at {path}")
        with open(path, newline="") as f:
            text = f.read()
        if not text:
            return []
        if not text.endswith("\n"):
            text = text[: text.rfind("\n") + 1]  # the torn last row
        reader = csv.DictReader(io.StringIO(text, newline=""))
        if tuple(reader.fieldnames or ()) != tuple(fields):
            raise ValueError(f"{path} has the columns {reader.fieldnames}, expected {list(fields)}: not a record "
                             "file of this kind of run (or written by another version); use another output folder")
        rows = []
        for row in reader:
            if None in row or any(v is None for v in row.values()):
                continue
            if is_complete is not None and not is_complete(row):
                continue
            rows.append(row)
        return rows if key is None else first_of_each_key(rows, key, path)

    def key(self, row: dict[str, Any]) -> tuple[str, ...]:
        """The identifying columns of ``row``, as strings."""
        return tuple(str(row[k]) for k in self.key_fields)

    def __contains__(self, key: tuple[Any, ...] | dict[str, Any]) -> bool:
        return self.get(key) is not None

    def get(self, key: tuple[Any, ...] | dict[str, Any]) -> dict[str, str] | None:
        """The record with this key (a tuple of the key columns' values, or a row), or None."""
        wanted = self.key(key) if isinstance(key, dict) else tuple(str(k) for k in key)
        return self._by_key.get(wanted)

    def __len__(self) -> int:
        return len(self.rows)

    # ------------------------------------------------------------------ writing

    def append(self, row: dict[str, Any]) -> None:
        """Write one finished record (fsync'd before returning)."""
        unknown = sorted(set(row) - set(self.fields))
        if unknown:
            raise ValueError(f"record has columns {unknown} that {self.path.name} does not have")
        self._writer.writerow({k: row.get(k, "") for k in self.fields})
        self._flush()
        stored = {k: str(row.get(k, "")) for k in self.fields}
        self.rows.append(stored)
        self._by_key[self.key(stored)] = stored

    def close(self) -> None:
        self._file.close()
        self._claim.release()

    def __enter__(self) -> RecordStore:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _flush(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())

    def _cut_torn_tail(self) -> None:
        """Drop a last row that a killed process left without its newline."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return
        data = self.path.read_bytes()
        if data.endswith(b"\n"):
            return
        with open(self.path, "r+b") as f:
            f.truncate(data.rfind(b"\n") + 1)
            f.flush()
            os.fsync(f.fileno())

    def _guard_settings(self, settings: dict[str, Any]) -> None:
        settings = json.loads(json.dumps(settings))  # the form they take on disk (tuples -> lists)
        if self.rows and self.settings_path.exists():
            saved = json.loads(self.settings_path.read_text())
            changed = {k: (saved.get(k), settings.get(k)) for k in sorted(set(saved) | set(settings))
                       if saved.get(k) != settings.get(k)}
            if changed:
                detail = "; ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in changed.items())
                raise SettingsMismatch(
                    f"{self.path.parent} holds {len(self.rows)} records made with other settings ({detail}); "
                    "use the same settings to resume, or another output folder")
            return
        _fsync_write(self.settings_path, json.dumps(settings, indent=2))
