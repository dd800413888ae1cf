"""Objects for clutter scenes: a built-in procedural set, or any folder of meshes.

Procedural objects need no download: boxes, cylinders, spheres, capsules, random convex
shapes, and composites (bottles, mugs, L-shapes), sized so that the Panda hand (8 cm
opening) can grasp them. Every object is a union of convex parts, so its collision
shape is exact and no convex decomposition is needed.

Mesh folders (``.obj`` / ``.stl`` / ``.glb``, e.g. ManiSkill's YCB once downloaded) are
decomposed into convex parts with CoACD; decompositions are cached on disk.

Object frame: z up, origin at the centre of the object's footprint, bottom at z = 0, so
an object standing upright on the table has its pose's z = 0.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from rtv3_maniskill.tasks.scene_geometry import CollisionShape, ObjectGeometry

PROCEDURAL_KINDS = ("box", "cylinder", "sphere", "capsule", "convex", "bottle", "mug", "lshape")
MESH_SUFFIXES = (".obj", ".stl", ".glb")
CACHE_DIR = Path(os.environ.get("RTV3_CACHE_DIR", Path.home() / ".cache" / "rtv3_maniskill"))

# Rotation taking SAPIEN's cylinder/capsule axis (x) to the object's z axis.
_X_TO_Z = trimesh.transformations.rotation_matrix(-np.pi / 2, [0, 1, 0])


def _translate(x: float, y: float, z: float, base: np.ndarray | None = None) -> np.ndarray:
    pose = np.eye(4) if base is None else base.copy()
    pose[:3, 3] = [x, y, z]
    return pose


def _random_color(rng: np.random.Generator) -> tuple[float, float, float, float]:
    hsv = np.array([[rng.uniform(0, 1), rng.uniform(0.4, 0.9), rng.uniform(0.5, 0.95)]])
    import matplotlib.colors as mcolors

    r, g, b = mcolors.hsv_to_rgb(hsv)[0]
    return (float(r), float(g), float(b), 1.0)


def _upright_cylinder(radius: float, half_length: float, z0: float, kind: str = "cylinder") -> CollisionShape:
    """A cylinder/capsule standing on z = z0 (its lowest point), axis along object z."""
    bottom = half_length + (radius if kind == "capsule" else 0.0)
    return CollisionShape(kind, (radius, half_length), _translate(0, 0, z0 + bottom, _X_TO_Z))


def _make_object(name: str, shapes: list[CollisionShape], rng: np.random.Generator) -> ObjectGeometry:
    obj = ObjectGeometry(name=name, shapes=shapes, visual_mesh=trimesh.Trimesh(), color=_random_color(rng))
    obj.visual_mesh = obj.collision_mesh()
    return obj


def make_procedural_object(kind: str, rng: np.random.Generator, scale: float = 1.0) -> ObjectGeometry:
    """One random object of ``kind`` (see ``PROCEDURAL_KINDS``); sizes in metres times ``scale``."""
    u = lambda lo, hi: float(rng.uniform(lo, hi)) * scale  # noqa: E731
    if kind == "box":
        hx, hy, hz = u(0.015, 0.035), u(0.015, 0.035), u(0.015, 0.06)
        shapes = [CollisionShape("box", (hx, hy, hz), _translate(0, 0, hz))]
    elif kind == "cylinder":
        shapes = [_upright_cylinder(u(0.018, 0.035), u(0.025, 0.07), 0.0)]
    elif kind == "sphere":
        r = u(0.022, 0.035)
        shapes = [CollisionShape("sphere", (r,), _translate(0, 0, r))]
    elif kind == "capsule":
        shapes = [_upright_cylinder(u(0.015, 0.03), u(0.02, 0.05), 0.0, kind="capsule")]
    elif kind == "convex":
        semi_axes = np.array([u(0.015, 0.035), u(0.015, 0.035), u(0.02, 0.05)])
        directions = rng.normal(size=(int(rng.integers(10, 20)), 3))
        points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * semi_axes
        hull = trimesh.convex.convex_hull(points)
        vertices = hull.vertices - [0.0, 0.0, hull.vertices[:, 2].min()]
        shapes = [CollisionShape("convex", (), np.eye(4), vertices)]
    elif kind == "bottle":
        r_body, h_body = u(0.025, 0.035), u(0.04, 0.06)
        r_neck, h_neck = u(0.01, 0.015), u(0.015, 0.03)
        shapes = [
            _upright_cylinder(r_body, h_body, 0.0),
            _upright_cylinder(r_neck, h_neck, 2 * h_body),
        ]
    elif kind == "mug":
        r, h = u(0.028, 0.035), u(0.03, 0.045)
        t = 0.006 * scale
        reach = u(0.02, 0.03)
        shapes = [
            _upright_cylinder(r, h, 0.0),
            CollisionShape("box", (reach / 2, t, t), _translate(r + reach / 2 - t, 0, 1.6 * h)),
            CollisionShape("box", (reach / 2, t, t), _translate(r + reach / 2 - t, 0, 0.4 * h)),
            CollisionShape("box", (t, t, 0.6 * h + t), _translate(r + reach - t, 0, h)),
        ]
    elif kind == "lshape":
        a, b, w, hz = u(0.04, 0.07), u(0.03, 0.05), u(0.012, 0.02), u(0.015, 0.025)
        shapes = [
            CollisionShape("box", (a, w, hz), _translate(0, 0, hz)),
            CollisionShape("box", (w, b, hz), _translate(a - w, b + w, hz)),
        ]
    else:
        raise ValueError(f"unknown procedural object kind {kind!r}; expected one of {PROCEDURAL_KINDS}")
    return _make_object(kind, shapes, rng)


class ProceduralObjectSet:
    """Draws random procedural objects of the given kinds."""

    def __init__(self, kinds: tuple[str, ...] = PROCEDURAL_KINDS):
        unknown = [k for k in kinds if k not in PROCEDURAL_KINDS]
        if unknown or not kinds:
            raise ValueError(f"unknown procedural object kinds {unknown or kinds}; expected some of {PROCEDURAL_KINDS}")
        self.kinds = tuple(kinds)

    def sample(self, rng: np.random.Generator, scale: float = 1.0) -> ObjectGeometry:
        return make_procedural_object(self.kinds[int(rng.integers(len(self.kinds)))], rng, scale)


def _file_digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()[:16]


def _convex_decomposition(mesh: trimesh.Trimesh, key: str, threshold: float) -> list[np.ndarray]:
    """CoACD convex parts (vertex arrays) of ``mesh``, cached under ``CACHE_DIR``."""
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
            hulls = _convex_decomposition(mesh, f"{_file_digest(path)}-{scale:.5f}", self.coacd_threshold)
            shapes = [CollisionShape("convex", (), np.eye(4), h) for h in hulls]
            obj = ObjectGeometry(name=path.stem, shapes=shapes, visual_mesh=mesh, mesh_file=str(path))
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


ObjectSet = ProceduralObjectSet | MeshFolderObjectSet


def make_object_set(source: str = "procedural") -> ObjectSet:
    """``"procedural"`` (built in), ``"procedural:box,mug"`` (some kinds) or a mesh folder path."""
    if source == "procedural":
        return ProceduralObjectSet()
    if source.startswith("procedural:"):
        return ProceduralObjectSet(tuple(k.strip() for k in source.split(":", 1)[1].split(",") if k.strip()))
    return MeshFolderObjectSet(source)


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


SampleObject = Callable[[np.random.Generator, float], ObjectGeometry]
