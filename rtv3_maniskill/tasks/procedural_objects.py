"""Procedural objects for clutter scenes, no download: boxes, cylinders, spheres, capsules, random
convex shapes, and composites (bottles, mugs, L-shapes).

Sizes (m) are drawn so that the Panda hand (8 cm opening) can grasp them. Every object is a union
of convex parts, so its collision shape is exact and no convex decomposition is needed. Object
frame: z up, origin at the centre of the footprint, bottom at z = 0.
"""

from __future__ import annotations

import matplotlib.colors as mcolors
import numpy as np
import trimesh

from rtv3_maniskill.robot.scene_geometry import CollisionShape, ObjectGeometry, translation, upright_cylinder

PROCEDURAL_KINDS = ("box", "cylinder", "sphere", "capsule", "convex", "bottle", "mug", "lshape")


def _random_color(rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A random saturated RGBA colour."""
    hsv = np.array([[rng.uniform(0, 1), rng.uniform(0.4, 0.9), rng.uniform(0.5, 0.95)]])
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
