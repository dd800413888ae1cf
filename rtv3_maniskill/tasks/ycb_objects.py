"""YCB-sized objects without a download: the graspable YCB objects at their nominal dimensions.

The RT-V3 authors validate shared control on YCB "packed" scenes (docs/PAPER_DETAILS.md,
"Authors' benchmark protocol"). ManiSkill's YCB meshes are a separate download, so this set
rebuilds the objects that matter for grasping from convex primitives at their published sizes
(metres; boxes x, y, z; cylinders radius, height), standing upright: boxes, cans and bottles
whose widths and heights are what make the scenes hard (tall objects next to the approach,
faces wider than the 8 cm opening). Every part is convex, so collisions are exact.

Object frame as in :mod:`rtv3_maniskill.tasks.object_library`: z up, origin at the centre of
the footprint, bottom at z = 0. ``scale`` multiplies every size (the authors' scenes use 0.8).
"""

from __future__ import annotations

import numpy as np
import trimesh

from rtv3_maniskill.robot.scene_geometry import CollisionShape, ObjectGeometry, translation, upright_cylinder

YCB_BOXES: dict[str, tuple[float, float, float]] = {
    "cracker_box": (0.060, 0.158, 0.210),
    "sugar_box": (0.038, 0.089, 0.175),
    "pudding_box": (0.035, 0.110, 0.089),
    "gelatin_box": (0.028, 0.085, 0.073),
    "potted_meat_can": (0.050, 0.097, 0.082),
}
"""Box-shaped YCB objects: full extents x, y, z (m)."""
YCB_CYLINDERS: dict[str, tuple[float, float]] = {
    "chips_can": (0.038, 0.250),
    "master_chef_can": (0.051, 0.140),
    "tomato_soup_can": (0.034, 0.102),
    "tuna_fish_can": (0.0425, 0.033),
}
"""Cylindrical YCB objects: radius, height (m)."""
YCB_BOTTLES: dict[str, tuple[float, float, float, float, float]] = {
    "mustard_bottle": (0.053, 0.093, 0.155, 0.014, 0.035),
    "bleach_cleanser": (0.050, 0.102, 0.200, 0.016, 0.050),
}
"""Bottles: body box x, y, z, then cap radius and height (m); the cap stands off-centre along y."""
YCB_MUG = (0.040, 0.081)
"""Mug: body radius and height (m), plus a handle of 2.4 cm reach."""
YCB_NAMES = (*YCB_BOXES, *YCB_CYLINDERS, *YCB_BOTTLES, "mug")

_COLORS = {
    "cracker_box": (0.80, 0.15, 0.12), "sugar_box": (0.95, 0.85, 0.35), "pudding_box": (0.55, 0.35, 0.20),
    "gelatin_box": (0.85, 0.30, 0.40), "potted_meat_can": (0.20, 0.35, 0.75), "chips_can": (0.90, 0.55, 0.10),
    "master_chef_can": (0.15, 0.45, 0.70), "tomato_soup_can": (0.85, 0.20, 0.20), "tuna_fish_can": (0.30, 0.55, 0.85),
    "mustard_bottle": (0.95, 0.80, 0.10), "bleach_cleanser": (0.92, 0.92, 0.95), "mug": (0.75, 0.20, 0.15),
}


def _box(x: float, y: float, z: float, base: float = 0.0, dy: float = 0.0) -> CollisionShape:
    return CollisionShape("box", (x / 2, y / 2, z / 2), translation(0.0, dy, base + z / 2))


def make_ycb_object(name: str, scale: float = 1.0) -> ObjectGeometry:
    """The YCB object ``name`` (one of :data:`YCB_NAMES`) standing upright, sizes times ``scale``."""
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    s = float(scale)
    if name in YCB_BOXES:
        shapes = [_box(*(s * v for v in YCB_BOXES[name]))]
    elif name in YCB_CYLINDERS:
        radius, height = YCB_CYLINDERS[name]
        shapes = [upright_cylinder(s * radius, s * height / 2, 0.0)]
    elif name in YCB_BOTTLES:
        x, y, z, cap_r, cap_h = (s * v for v in YCB_BOTTLES[name])
        cap = upright_cylinder(cap_r, cap_h / 2, z)
        cap.local_pose[1, 3] = y / 2 - cap_r - 0.1 * y  # the spout sits towards one end, as on the real bottles
        shapes = [_box(x, y, z), cap]
    elif name == "mug":
        radius, height = (s * v for v in YCB_MUG)
        t, reach = 0.006 * s, 0.024 * s
        shapes = [
            upright_cylinder(radius, height / 2, 0.0),
            CollisionShape("box", (reach / 2, t, t), translation(radius + reach / 2 - t, 0, 0.8 * height)),
            CollisionShape("box", (reach / 2, t, t), translation(radius + reach / 2 - t, 0, 0.2 * height)),
            CollisionShape("box", (t, t, 0.3 * height + t), translation(radius + reach - t, 0, 0.5 * height)),
        ]
    else:
        raise ValueError(f"unknown YCB object {name!r}; expected one of {YCB_NAMES}")
    obj = ObjectGeometry(name=name, shapes=shapes, visual_mesh=trimesh.Trimesh(), color=(*_COLORS[name], 1.0))
    obj.visual_mesh = obj.collision_mesh()
    return obj


class YcbObjectSet:
    """The YCB-sized objects of :data:`YCB_NAMES` (``object_source="ycb"``); ``names`` selects some."""

    def __init__(self, names: tuple[str, ...] = YCB_NAMES):
        unknown = [n for n in names if n not in YCB_NAMES]
        if unknown or not names:
            raise ValueError(f"unknown YCB objects {unknown or names}; expected some of {YCB_NAMES}")
        self.names = tuple(names)

    def sample(self, rng: np.random.Generator, scale: float = 1.0) -> ObjectGeometry:
        """One object drawn uniformly, sizes times ``scale``."""
        return make_ycb_object(self.names[int(rng.integers(len(self.names)))], scale)

    def sample_distinct(self, rng: np.random.Generator, count: int, scale: float = 1.0) -> list[ObjectGeometry]:
        """``min(count, len(names))`` different objects, sizes times ``scale``."""
        picks = rng.choice(len(self.names), size=min(int(count), len(self.names)), replace=False)
        return [make_ycb_object(self.names[int(i)], scale) for i in picks]
