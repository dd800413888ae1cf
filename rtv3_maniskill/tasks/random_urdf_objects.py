"""The ~1000 random objects that the ``pybullet`` package ships in ``pybullet_data/random_urdfs`` (no download).

Their meshes already are convex decompositions (one ``o convex_i`` group per part); they are
normalised to sizes the Panda hand can grasp (VGN-like, a few cm to 12 cm) and stood on a
stable side. Normalised objects are cached on disk (:mod:`rtv3_maniskill.tasks.convex_cache`).
Object frame: z up, origin at the centre of the footprint, bottom at z = 0.
"""

from __future__ import annotations

import hashlib
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from rtv3_maniskill.robot.scene_geometry import CollisionShape, ObjectGeometry
from rtv3_maniskill.tasks import convex_cache

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
        cache = convex_cache.CACHE_DIR / RANDOM_URDFS / f"{digest.hexdigest()[:20]}.npz"
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
                key = f"{convex_cache.file_digest(mesh_path)}-{mesh_scale:.5f}"
                hulls = convex_cache.convex_decomposition(whole, key, self.coacd_threshold)
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
