"""Object sets for clutter scenes, by name: ``make_object_set(source)``.

Sources: the built-in procedural objects (:mod:`~rtv3_maniskill.tasks.procedural_objects`),
YCB-sized objects (:mod:`~rtv3_maniskill.tasks.ycb_objects`), pybullet's random objects
(:mod:`~rtv3_maniskill.tasks.random_urdf_objects`), any folder of meshes
(:mod:`~rtv3_maniskill.tasks.mesh_folder_objects`), or several of these mixed. Every set has
``sample(rng, scale) -> ObjectGeometry``.

Object frame: z up, origin at the centre of the object's footprint, bottom at z = 0, so
an object standing upright on the table has its pose's z = 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rtv3_maniskill.robot.scene_geometry import ObjectGeometry
from rtv3_maniskill.tasks.mesh_folder_objects import MeshFolderObjectSet
from rtv3_maniskill.tasks.procedural_objects import ProceduralObjectSet
from rtv3_maniskill.tasks.random_urdf_objects import RANDOM_URDFS, RandomUrdfObjectSet
from rtv3_maniskill.tasks.ycb_objects import YcbObjectSet


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
