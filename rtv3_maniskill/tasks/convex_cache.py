"""Disk cache of convex parts (under ``RTV3_CACHE_DIR``, default ``~/.cache/rtv3_maniskill``).

CoACD convex decompositions of meshes, keyed by the mesh file's content and scale, and convex
parts written as ``.obj`` files for SAPIEN to load, keyed by their vertices. Writes go through a
temporary file and a rename, so parallel workers never read a half-written entry.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import trimesh

CACHE_DIR = Path(os.environ.get("RTV3_CACHE_DIR", Path.home() / ".cache" / "rtv3_maniskill"))


def file_digest(path: Path) -> str:
    """First 16 hex digits of the SHA-1 of a file's bytes (a cache key)."""
    return hashlib.sha1(path.read_bytes()).hexdigest()[:16]


def convex_decomposition(mesh: trimesh.Trimesh, key: str, threshold: float) -> list[np.ndarray]:
    """CoACD convex parts (vertex arrays ``(V_i, 3)``) of ``mesh``, cached under ``CACHE_DIR`` by ``key``."""
    cache = CACHE_DIR / "coacd" / f"{key}-{threshold:g}.npz"
    if cache.exists():
        with np.load(cache) as data:
            return [data[k] for k in sorted(data.files, key=lambda s: int(s[1:]))]
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)), threshold=threshold)
    hulls = [np.asarray(v, dtype=np.float64) for v, _ in parts]
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, **{f"p{i}": h for i, h in enumerate(hulls)})
    tmp.replace(cache)
    return hulls


def convex_part_file(vertices: np.ndarray) -> str:
    """Write a convex part as an ``.obj`` (content-addressed cache) for SAPIEN to load."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    key = hashlib.sha1(vertices.tobytes()).hexdigest()[:20]
    path = CACHE_DIR / "convex" / f"{key}.obj"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.obj")
        trimesh.convex.convex_hull(vertices).export(tmp)
        tmp.replace(path)
    return str(path)
