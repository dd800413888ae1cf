"""Objects for clutter scenes: a built-in procedural set, or any folder of meshes.

Procedural objects need no download: boxes, cylinders, spheres, capsules, random convex
shapes, and composites (bottles, mugs, L-shapes), sized so that the Panda hand (8 cm
opening) can grasp them. Every object is a union of convex parts, so its collision
shape is exact and no convex decomposition is needed.

Mesh folders (``.obj`` / ``.stl`` / ``.glb``, e.g. ManiSkill's YCB once downloaded) are
decomposed into convex parts with CoACD; decompositions are cached on disk.

``"random_urdfs"``: the ~1000 random objects that the ``pybullet`` package ships in
``pybullet_data/random_urdfs`` (no download), whose meshes already are convex decompositions
(one ``o convex_i`` group per part), normalised to sizes the Panda hand can grasp (VGN-like,
a few cm to 11 cm). ``"procedural+random_urdfs"`` draws each object from either set.

Object frame: z up, origin at the centre of the object's footprint, bottom at z = 0, so
an object standing upright on the table has its pose's z = 0.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from rtv3_maniskill.robot.scene_geometry import CollisionShape, ObjectGeometry, translation, upright_cylinder
from rtv3_maniskill.tasks.ycb_objects import YcbObjectSet

PROCEDURAL_KINDS = ("box", "cylinder", "sphere", "capsule", "convex", "bottle", "mug", "lshape")
MESH_SUFFIXES = (".obj", ".stl", ".glb")
CACHE_DIR = Path(os.environ.get("RTV3_CACHE_DIR", Path.home() / ".cache" / "rtv3_maniskill"))

def _random_color(rng: np.random.Generator) -> tuple[float, float, float, float]:
    hsv = np.array([[rng.uniform(0, 1), rng.uniform(0.4, 0.9), rng.uniform(0.5, 0.95)]])
    import matplotlib.colors as mcolors

    r, g, b = mcolors.hsv_to_rgb(hsv)[0]
    return (float(r), float(g), float(b), 1.0)


def _make_object(name: str, shapes: list[CollisionShape], rng: np.random.Generator) -> ObjectGeometry:
    obj = ObjectGeometry(name=name, shapes=shapes, visual_mesh=trimesh.Trimesh(), color=_random_color(rng))
    obj.visual_mesh = obj.collision_mesh()
    return obj


def make_procedural_object(kind: str, rng: np.random.Generator, scale: float = 1.0) -> ObjectGeometry:
    """One random object of ``kind`` (see ``PROCEDURAL_KINDS``); sizes in metres times ``scale``."""
    u = lambda lo, hi: float(rng.uniform(lo, hi)) * scale  # noqa: E731
    if kind == "box":
        hx, hy, hz = u(0.015, 0.035), u(0.015, 0.035), u(0.015, 0.06)
        shapes = [CollisionShape("box", (hx, hy, hz), translation(0, 0, hz))]
    elif kind == "cylinder":
        shapes = [upright_cylinder(u(0.018, 0.035), u(0.025, 0.07), 0.0)]
    elif kind == "sphere":
        r = u(0.022, 0.035)
        shapes = [CollisionShape("sphere", (r,), translation(0, 0, r))]
    elif kind == "capsule":
        shapes = [upright_cylinder(u(0.015, 0.03), u(0.02, 0.05), 0.0, kind="capsule")]
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
            upright_cylinder(r_body, h_body, 0.0),
            upright_cylinder(r_neck, h_neck, 2 * h_body),
        ]
    elif kind == "mug":
        r, h = u(0.028, 0.035), u(0.03, 0.045)
        t = 0.006 * scale
        reach = u(0.02, 0.03)
        shapes = [
            upright_cylinder(r, h, 0.0),
            CollisionShape("box", (reach / 2, t, t), translation(r + reach / 2 - t, 0, 1.6 * h)),
            CollisionShape("box", (reach / 2, t, t), translation(r + reach / 2 - t, 0, 0.4 * h)),
            CollisionShape("box", (t, t, 0.6 * h + t), translation(r + reach - t, 0, h)),
        ]
    elif kind == "lshape":
        a, b, w, hz = u(0.04, 0.07), u(0.03, 0.05), u(0.012, 0.02), u(0.015, 0.025)
        shapes = [
            CollisionShape("box", (a, w, hz), translation(0, 0, hz)),
            CollisionShape("box", (w, b, hz), translation(a - w, b + w, hz)),
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
            hulls = _convex_decomposition(mesh, f"{_file_digest(path)}-{scale:.5f}", self.coacd_threshold)
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


RANDOM_URDFS = "random_urdfs"
RANDOM_URDF_MAX_PARTS = 32
"""Objects with more convex parts are skipped (slow to build; a few percent of the set)."""
RANDOM_URDF_MAX_EXTENT = 0.12
"""Longest side (m) of a normalised object at scene scale 1.0 (VGN objects: a few cm to ~10 cm)."""
RANDOM_URDF_MIN_EXTENT = 0.05
RANDOM_URDF_MAX_MIDDLE = 0.065
"""Middle side cap (m): an object lying on its largest face fits between the fingers (8 cm) with room to spare."""
RANDOM_URDF_MAX_WIDTH = 0.055
"""Smallest side cap (m): every object has a grasp width well inside the 8 cm opening (implied by the middle cap)."""
RANDOM_URDF_MIN_WIDTH = 0.008
_RANDOM_URDF_SETTINGS = (
    f"v6-{RANDOM_URDF_MAX_PARTS}-{RANDOM_URDF_MAX_EXTENT}-{RANDOM_URDF_MIN_EXTENT}-{RANDOM_URDF_MAX_MIDDLE}-"
    f"{RANDOM_URDF_MAX_WIDTH}-{RANDOM_URDF_MIN_WIDTH}"
)
"""Part of the disk cache key: changing the normalisation rebuilds the cached objects."""


def random_urdfs_folder() -> Path:
    """``pybullet_data/random_urdfs`` of the installed ``pybullet`` package."""
    try:
        import pybullet_data
    except ImportError:
        raise ImportError(
            'object_source "random_urdfs" needs the pybullet package (pip install "pybullet>=3.2.5,<3.3"), '
            "which ships the objects in pybullet_data/random_urdfs"
        ) from None
    return Path(pybullet_data.getDataPath()) / RANDOM_URDFS


def _read_obj_parts(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(vertices, triangles) of each ``o`` / ``g`` group of an ``.obj`` file (the whole file when it has none)."""
    vertices: list[list[float]] = []
    groups: list[list[list[int]]] = []
    current: list[list[int]] | None = None
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith(("o ", "g ")):
                current = []
                groups.append(current)
            elif line.startswith("f "):
                if current is None:
                    current = []
                    groups.append(current)
                ids = [int(t.split("/")[0]) for t in line.split()[1:]]
                ids = [i - 1 if i > 0 else len(vertices) + i for i in ids]
                current.extend([ids[0], ids[k], ids[k + 1]] for k in range(1, len(ids) - 1))
    points = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    parts = []
    for faces in groups:
        if not faces:
            continue
        faces_array = np.asarray(faces, dtype=np.int64)
        used, local = np.unique(faces_array, return_inverse=True)
        parts.append((points[used], local.reshape(-1, 3)))
    return parts


def _read_urdf(path: Path) -> tuple[str, float, tuple[float, float, float, float]]:
    """Collision mesh file name, its (uniform) scale and the visual colour of a one-link URDF."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    mesh = root.find(".//collision/geometry/mesh")
    if mesh is None:
        mesh = root.find(".//visual/geometry/mesh")
    if mesh is None or not mesh.get("filename"):
        raise ValueError(f"{str(path)!r} has no mesh geometry")
    scales = [float(x) for x in (mesh.get("scale") or "1 1 1").split()]
    color = root.find(".//visual/material/color")
    rgba = (0.6, 0.6, 0.6, 1.0)
    if color is not None and color.get("rgba"):
        values = [float(x) for x in color.get("rgba").split()]
        rgba = (values[0], values[1], values[2], 1.0)
    return str(mesh.get("filename")), float(np.mean(scales)), rgba


def _is_convex(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether a closed triangle mesh fills (97 %) its convex hull."""
    from scipy.spatial import ConvexHull

    hull_volume = ConvexHull(vertices).volume
    part_volume = abs(trimesh.Trimesh(vertices, faces, process=False).volume)
    return hull_volume > 0 and part_volume >= 0.97 * hull_volume


def _normalising_transform(points: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The frame and scale of a random_urdfs object: oriented-bounding-box axes (middle side along
    x, smallest along y, longest along z), scaled to graspable VGN-like sizes; None when the object
    cannot be made graspable (a thin sheet)."""
    to_obb, extents = trimesh.bounds.oriented_bounds(points)
    order = np.argsort(extents)  # smallest, middle, largest
    small, middle, large = extents[order]
    if large <= 0 or small / large < 0.1:
        return None
    scale = min(RANDOM_URDF_MAX_EXTENT / large, RANDOM_URDF_MAX_MIDDLE / middle, RANDOM_URDF_MAX_WIDTH / small)
    scale = max(scale, RANDOM_URDF_MIN_EXTENT / large)
    if scale * small < RANDOM_URDF_MIN_WIDTH or scale * middle > RANDOM_URDF_MAX_MIDDLE + 1e-9:
        return None
    permute = np.zeros((4, 4))
    permute[0, order[1]] = permute[1, order[0]] = permute[2, order[2]] = permute[3, 3] = 1.0
    if np.linalg.det(permute[:3, :3]) < 0:
        permute[0] *= -1
    transform = np.diag([scale, scale, scale, 1.0]) @ permute @ to_obb
    moved = trimesh.transform_points(points, transform)
    lo, hi = moved.min(axis=0), moved.max(axis=0)
    transform[:3, 3] += [-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]]
    return transform, scale


def _upright_rotation(hulls: list[np.ndarray], meshes: list[trimesh.Trimesh]) -> np.ndarray:
    """The tallest statically stable way to stand an object whose bounding box is axis-aligned.

    Candidates: each box axis pointing up (longest first) with either sign. Stable: the object
    must be tilted by 15 degrees or more before its centre of mass leaves the support polygon
    (the points within 0.5 mm of the bottom). Falls back to the flattest pose.
    """
    from scipy.spatial import ConvexHull, QhullError

    volumes = np.array([m.volume for m in meshes])
    com = (np.array([m.center_mass for m in meshes]) * volumes[:, None]).sum(axis=0) / volumes.sum()
    points = np.concatenate(hulls)
    extents = points.max(axis=0) - points.min(axis=0)
    tip_angle = np.radians(15.0)
    candidates = []
    for axis in np.argsort(-extents):
        for sign in (1.0, -1.0):
            up = np.zeros(3)
            up[axis] = sign
            side = np.zeros(3)
            side[(axis + 1) % 3] = 1.0
            candidates.append(np.stack([side, np.cross(up, side), up]))  # rows: new x, y, z in old axes
    for rotation in candidates:
        moved = points @ rotation.T
        bottom = moved[:, 2].min()
        support = moved[moved[:, 2] <= bottom + 5e-4, :2]
        try:
            polygon = ConvexHull(support)
        except (QhullError, ValueError):
            continue
        centre = rotation @ com
        inside = -np.max(polygon.equations[:, :2] @ centre[:2] + polygon.equations[:, 2])
        if np.arctan2(inside, centre[2] - bottom) >= tip_angle:
            return rotation
    return candidates[-1]


class RandomUrdfObjectSet:
    """The random objects that ship with pybullet (``pybullet_data/random_urdfs``), no download.

    Each folder ``NNN/`` holds ``NNN.urdf`` and the mesh it names, an ``.obj`` that already is a
    convex decomposition (one ``o convex_i`` group per part, checked); a mesh with non-convex
    groups goes through CoACD (cached on disk like a mesh folder's). Objects are scaled to VGN-like
    graspable sizes (oriented bounding box: longest side 5-12 cm, middle side <= 6.5 cm, smallest
    0.8-5.5 cm) and stand on the tallest statically stable side of that box ("upright" for packed
    scenes; about a third stand on their longest side); the scene protocol's 0.8-1.0 / 0.7-0.9
    jitter is applied on top by ``sample``. Objects with non-finite vertices, more than
    ``RANDOM_URDF_MAX_PARTS`` parts or sheet-like shapes are skipped: ``sample`` redraws, which
    keeps the draw uniform over the valid objects and deterministic per ``rng``. Objects are
    read when first drawn (a few ms each) and kept in memory.
    """

    def __init__(self, folder: str | os.PathLike | None = None, coacd_threshold: float = 0.08):
        self.folder = random_urdfs_folder() if folder is None else Path(folder).expanduser()
        if not self.folder.is_dir():
            raise FileNotFoundError(
                f"random_urdfs folder {str(self.folder)!r} does not exist (it ships with the pybullet package: "
                'pip install "pybullet>=3.2.5,<3.3")'
            )
        self.urdfs = sorted(self.folder.glob("*/*.urdf"))
        if not self.urdfs:
            raise FileNotFoundError(f"random_urdfs folder {str(self.folder)!r} holds no */*.urdf objects")
        self.coacd_threshold = coacd_threshold
        self._loaded: dict[int, ObjectGeometry | None] = {}

    def __len__(self) -> int:
        return len(self.urdfs)

    def load(self, index: int) -> ObjectGeometry | None:
        """Object ``index`` (sorted by folder) at its normalised size; None when it is skipped."""
        if index not in self._loaded:
            self._loaded[index] = self._read(self.urdfs[index])
        return self._loaded[index]

    def _read(self, urdf: Path) -> ObjectGeometry | None:
        """The normalised object, from the disk cache (content-addressed) or built and cached there."""
        mesh_name, mesh_scale, color = _read_urdf(urdf)
        mesh_path = urdf.parent / mesh_name
        digest = hashlib.sha1(urdf.read_bytes() + mesh_path.read_bytes() + _RANDOM_URDF_SETTINGS.encode())
        cache = CACHE_DIR / RANDOM_URDFS / f"{digest.hexdigest()[:20]}.npz"
        if cache.exists():
            with np.load(cache) as data:
                if "skip" in data.files:
                    return None
                hulls = [data[f"p{i}"] for i in range(int(data["num_parts"]))]
                visual = trimesh.Trimesh(data["visual_vertices"], data["visual_faces"], process=False)
                scale = float(data["scale"])
        else:
            built = self._build(mesh_path, mesh_scale)
            cache.parent.mkdir(parents=True, exist_ok=True)
            tmp = cache.with_suffix(f".{os.getpid()}.tmp.npz")
            if built is None:
                np.savez(tmp, skip=np.ones(1))
            else:
                hulls, visual, scale = built
                np.savez(tmp, num_parts=len(hulls), visual_vertices=visual.vertices, visual_faces=visual.faces,
                         scale=scale, **{f"p{i}": h for i, h in enumerate(hulls)})
            tmp.replace(cache)
            if built is None:
                return None
        shapes = [CollisionShape("convex", (), np.eye(4), h) for h in hulls]
        obj = ObjectGeometry(name=f"urdf{urdf.stem}", shapes=shapes, visual_mesh=visual, color=color)
        obj.normalising_scale = scale  # type: ignore[attr-defined]
        return obj

    def _build(self, mesh_path: Path, mesh_scale: float) -> tuple[list[np.ndarray], trimesh.Trimesh, float] | None:
        """Convex parts (object frame, normalised size), visual mesh and overall scale; None to skip."""
        parts = _read_obj_parts(mesh_path)
        if not parts or len(parts) > RANDOM_URDF_MAX_PARTS:
            return None
        parts = [(v * mesh_scale, f) for v, f in parts]
        if not all(np.isfinite(v).all() and len(v) >= 4 for v, _ in parts):
            return None
        normalised = _normalising_transform(np.concatenate([v for v, _ in parts]))
        if normalised is None:
            return None
        transform, scale = normalised
        try:
            if all(_is_convex(v, f) for v, f in parts):
                hulls = [v for v, _ in parts]
            else:
                whole = trimesh.util.concatenate([trimesh.Trimesh(v, f, process=False) for v, f in parts])
                key = f"{_file_digest(mesh_path)}-{mesh_scale:.5f}"
                hulls = _convex_decomposition(whole, key, self.coacd_threshold)
            hulls = [trimesh.transform_points(h, transform) for h in hulls]
            meshes = [trimesh.convex.convex_hull(h) for h in hulls]
        except Exception:  # qhull errors on degenerate (flat) parts
            return None
        if any(m.volume <= 1e-9 for m in meshes):  # degenerate parts cannot be built into the simulator
            return None
        # Stand the object on a stable side, as tall as it stays; then footprint centre at the
        # origin and bottom at z = 0 (on the parts themselves: CoACD's hulls differ slightly from the mesh).
        upright = np.eye(4)
        upright[:3, :3] = _upright_rotation(hulls, meshes)
        hulls = [h @ upright[:3, :3].T for h in hulls]
        lo, hi = np.min([h.min(axis=0) for h in hulls], axis=0), np.max([h.max(axis=0) for h in hulls], axis=0)
        upright[:3, 3] = -np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
        hulls = [h + upright[:3, 3] for h in hulls]
        for mesh in meshes:
            mesh.apply_transform(upright)
        return hulls, trimesh.util.concatenate(meshes), scale * mesh_scale

    def sample(self, rng: np.random.Generator, scale: float = 1.0) -> ObjectGeometry:
        for _ in range(1000):
            base = self.load(int(rng.integers(len(self.urdfs))))
            if base is not None:
                break
        else:
            raise RuntimeError(f"no usable object in {str(self.folder)!r} after 1000 draws")
        if scale == 1.0:
            return base
        shapes = [CollisionShape("convex", (), np.eye(4), s.vertices * scale) for s in base.shapes]
        visual = base.visual_mesh.copy()
        visual.apply_scale(scale)
        return ObjectGeometry(name=base.name, shapes=shapes, visual_mesh=visual, color=base.color)


class MixedObjectSet:
    """Each object drawn from one of several sets, uniformly (e.g. ``"procedural+random_urdfs"``)."""

    def __init__(self, sets: list):
        if not sets:
            raise ValueError("a mixed object set needs at least one set")
        self.sets = list(sets)

    def sample(self, rng: np.random.Generator, scale: float = 1.0) -> ObjectGeometry:
        return self.sets[int(rng.integers(len(self.sets)))].sample(rng, scale)


ObjectSet = ProceduralObjectSet | MeshFolderObjectSet | RandomUrdfObjectSet | MixedObjectSet | YcbObjectSet
YCB = "ycb"


def make_object_set(source: str = "procedural") -> ObjectSet:
    """``"procedural"`` (built in), ``"procedural:box,mug"`` (some kinds), ``"ycb"`` (YCB objects at their
    nominal sizes, built in; ``"ycb:mug,chips_can"`` some of them), ``"random_urdfs"`` (pybullet's
    random objects; ``"random_urdfs:FOLDER"`` for another copy of that folder), several of these joined
    with ``+`` (each object from one of them, e.g. ``"procedural+random_urdfs"``) or a mesh folder path."""
    if source == "procedural":
        return ProceduralObjectSet()
    if source.startswith("procedural:"):
        return ProceduralObjectSet(tuple(k.strip() for k in source.split(":", 1)[1].split(",") if k.strip()))
    if source == YCB:
        return YcbObjectSet()
    if source.startswith(YCB + ":"):
        return YcbObjectSet(tuple(n.strip() for n in source.split(":", 1)[1].split(",") if n.strip()))
    if source == RANDOM_URDFS:
        return RandomUrdfObjectSet()
    if source.startswith(RANDOM_URDFS + ":"):
        return RandomUrdfObjectSet(source.split(":", 1)[1])
    if "+" in source and not Path(source).expanduser().exists():
        return MixedObjectSet([make_object_set(part.strip()) for part in source.split("+") if part.strip()])
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
