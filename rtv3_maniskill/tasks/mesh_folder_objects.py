"""Objects from a folder of meshes (``.obj`` / ``.stl`` / ``.glb``, e.g. ManiSkill's YCB once downloaded).

Each mesh is decomposed into convex parts with CoACD (cached on disk, see
:mod:`rtv3_maniskill.tasks.convex_cache`). Object frame: z up, origin at the centre of the
footprint, bottom at z = 0.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh

from rtv3_maniskill.robot.scene_geometry import CollisionShape, ObjectGeometry
from rtv3_maniskill.tasks.convex_cache import convex_decomposition, file_digest

MESH_SUFFIXES = (".obj", ".stl", ".glb")


class MeshFolderObjectSet:
    """Objects from a folder of meshes (searched recursively).

    Meshes are used at their own scale when their largest extent lies within
    ``[0.02, 0.3]`` m, otherwise rescaled to 0.12 m (files in mm or cm). Files whose name
    contains ``collision`` are skipped (ManiSkill's YCB ships one next to each visual mesh).
    """

    def __init__(self, folder: str | os.PathLike, coacd_threshold: float = 0.08):
        self.folder = Path(folder).expanduser()
        if not self.folder.is_dir():
            raise FileNotFoundError(f"object folder {str(self.folder)!r} does not exist or is not a directory")
        self.files = sorted(
            p for p in self.folder.rglob("*") if p.suffix.lower() in MESH_SUFFIXES and "collision" not in p.name.lower()
        )
        if not self.files:
            raise FileNotFoundError(
                f"object folder {str(self.folder)!r} holds no mesh files ({', '.join(MESH_SUFFIXES)})"
            )
        self.coacd_threshold = coacd_threshold
        self._loaded: dict[Path, ObjectGeometry] = {}
        # An object's name: its file's stem, or its folder's name where stems repeat (ManiSkill's YCB:
        # every model is `<id>/textured.obj`), so that layouts asking for distinct objects get them.
        stems = [p.stem for p in self.files]
        self.names = {p: p.stem if stems.count(p.stem) == 1 else p.parent.name for p in self.files}

    def _load(self, path: Path) -> ObjectGeometry:
        if path not in self._loaded:
            mesh = trimesh.load(path, force="mesh")
            if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
                raise ValueError(f"mesh file {str(path)!r} holds no triangles")
            extent = float(mesh.extents.max())
            scale = 1.0 if 0.02 <= extent <= 0.3 else 0.12 / extent
            mesh.apply_scale(scale)
            # Object frame: footprint centre at the origin, bottom at z = 0.
            lo, hi = mesh.bounds
            offset = np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
            mesh.apply_translation(offset)
            hulls = convex_decomposition(mesh, f"{file_digest(path)}-{scale:.5f}", self.coacd_threshold)
            shapes = [CollisionShape("convex", (), np.eye(4), h) for h in hulls]
            obj = ObjectGeometry(name=self.names[path], shapes=shapes, visual_mesh=mesh, mesh_file=str(path))
            obj.mesh_scale = scale  # type: ignore[attr-defined]
            obj.mesh_offset = offset  # type: ignore[attr-defined]
            self._loaded[path] = obj
        return self._loaded[path]

    def sample(self, rng: np.random.Generator, scale: float = 1.0) -> ObjectGeometry:
        # Mesh objects keep their real size; `scale` is the VGN size jitter (0.7..1.0).
        base = self._load(self.files[int(rng.integers(len(self.files)))])
        if scale == 1.0:
            return base
        shapes = [CollisionShape("convex", (), np.eye(4), s.vertices * scale) for s in base.shapes]
        visual = base.visual_mesh.copy()
        visual.apply_scale(scale)
        obj = ObjectGeometry(name=base.name, shapes=shapes, visual_mesh=visual, mesh_file=base.mesh_file)
        obj.mesh_scale = base.mesh_scale * scale  # type: ignore[attr-defined]
        obj.mesh_offset = base.mesh_offset * scale  # type: ignore[attr-defined]
        return obj
