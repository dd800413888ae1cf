"""object_source="random_urdfs": pybullet's random objects as graspable convex unions, in GraspClutter-v1."""

from __future__ import annotations

import sys

import gymnasium as gym
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

import rtv3_maniskill  # noqa: F401  (registers the task)
from rtv3_maniskill.tasks import convex_cache
from rtv3_maniskill.tasks.object_library import MixedObjectSet, make_object_set
from rtv3_maniskill.tasks.procedural_objects import ProceduralObjectSet
from rtv3_maniskill.tasks.random_urdf_objects import (
    RANDOM_URDF_MAX_EXTENT,
    RANDOM_URDF_MAX_MIDDLE,
    RANDOM_URDF_MAX_PARTS,
    RANDOM_URDF_MAX_WIDTH,
    RANDOM_URDF_MIN_EXTENT,
    RandomUrdfObjectSet,
)

pytest.importorskip("pybullet_data")


@pytest.fixture(scope="module")
def urdf_set():
    return make_object_set("random_urdfs")


def _check_graspable_convex_union(obj, scale: float = 1.0):
    assert 1 <= len(obj.shapes) <= RANDOM_URDF_MAX_PARTS
    for shape in obj.shapes:
        assert shape.kind == "convex"
        assert np.isfinite(shape.vertices).all()
        hull = ConvexHull(shape.vertices)
        assert hull.volume > 1e-9
    small, middle, large = np.sort(obj.collision_mesh().extents)
    eps = 1e-6
    assert large <= RANDOM_URDF_MAX_EXTENT * scale + eps and large >= RANDOM_URDF_MIN_EXTENT * scale - eps
    assert middle <= RANDOM_URDF_MAX_MIDDLE * scale + eps
    assert small <= RANDOM_URDF_MAX_WIDTH * scale + eps, "some side must fit well inside the 8 cm opening"
    lo, hi = obj.collision_mesh().bounds
    assert abs(lo[2]) < 1e-9, "object frame: bottom at z = 0"
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)


def test_random_urdfs_set_loads_graspable_convex_unions(urdf_set):
    assert isinstance(urdf_set, RandomUrdfObjectSet)
    assert len(urdf_set) >= 900
    objects = [urdf_set.load(i) for i in range(0, len(urdf_set), 25)]
    valid = [o for o in objects if o is not None]
    assert len(valid) >= 0.85 * len(objects)
    for obj in valid:
        assert obj.name.startswith("urdf") and obj.mesh_file is None
        _check_graspable_convex_union(obj)
        assert len(obj.visual_mesh.faces) > 0


def test_random_urdfs_sample_is_seeded_and_scaled(urdf_set):
    draws = []
    for _ in range(2):
        rng = np.random.default_rng(7)
        draws.append([urdf_set.sample(rng, 0.8) for _ in range(4)])
    for a, b in zip(*draws):
        assert a.name == b.name
        for sa, sb in zip(a.shapes, b.shapes):
            np.testing.assert_array_equal(sa.vertices, sb.vertices)
        _check_graspable_convex_union(a, scale=0.8)


def test_mixed_source_draws_from_both_sets():
    mixed = make_object_set("procedural+random_urdfs")
    assert isinstance(mixed, MixedObjectSet)
    assert isinstance(mixed.sets[0], ProceduralObjectSet) and isinstance(mixed.sets[1], RandomUrdfObjectSet)
    rng = np.random.default_rng(0)
    names = {mixed.sample(rng, 1.0).name.startswith("urdf") for _ in range(20)}
    assert names == {True, False}


def test_missing_folder_or_package_is_a_clear_error(tmp_path, monkeypatch):
    with pytest.raises(FileNotFoundError, match="random_urdfs folder .*missing.* does not exist.*pybullet"):
        make_object_set(f"random_urdfs:{tmp_path / 'missing'}")
    with pytest.raises(FileNotFoundError, match="holds no"):
        make_object_set(f"random_urdfs:{tmp_path}")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        gym.make("GraspClutter-v1", obs_mode="state_dict", object_source=f"random_urdfs:{tmp_path / 'missing'}")
    monkeypatch.setitem(sys.modules, "pybullet_data", None)
    with pytest.raises(ImportError, match="needs the pybullet package"):
        make_object_set("random_urdfs")


def _write_object(folder, name: str, text: str) -> None:
    (folder / name).mkdir()
    (folder / name / f"{name}.obj").write_text(text)
    (folder / name / f"{name}.urdf").write_text(
        f'<robot name="{name}"><link name="l"><visual><geometry><mesh filename="{name}.obj" scale="0.01 0.01 0.01"/>'
        '</geometry><material name="m"><color rgba="0.1 0.2 0.3 1"/></material></visual>'
        f'<collision><geometry><mesh filename="{name}.obj" scale="0.01 0.01 0.01"/></geometry></collision>'
        "</link></robot>"
    )


def _obj_text(meshes: list[trimesh.Trimesh], groups: bool) -> str:
    lines, offset = [], 1
    for i, mesh in enumerate(meshes):
        if groups:
            lines.append(f"o convex_{i}")
        lines += [f"v {x} {y} {z}" for x, y, z in mesh.vertices]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in mesh.faces]
        offset += len(mesh.vertices)
    return "\n".join(lines) + "\n"


def test_non_convex_meshes_go_through_coacd_and_broken_ones_are_skipped(tmp_path, monkeypatch):
    monkeypatch.setattr(convex_cache, "CACHE_DIR", tmp_path / "cache")
    folder = tmp_path / "objects"
    folder.mkdir()
    # An L of two boxes as two groups (two convex parts); a ring as one group (not convex). Units: cm.
    a = trimesh.creation.box(extents=[6.0, 2.0, 2.0])
    b = trimesh.creation.box(extents=[2.0, 2.0, 6.0])
    b.apply_translation([2.0, 0.0, 4.0])
    _write_object(folder, "000", _obj_text([a, b], groups=True))
    ring = trimesh.creation.annulus(r_min=1.5, r_max=3.0, height=2.0)
    _write_object(folder, "001", _obj_text([ring], groups=False))
    _write_object(folder, "002", _obj_text([a], groups=True).replace("v ", "v nan ", 1))
    _write_object(folder, "003", _obj_text([trimesh.creation.box(extents=[2.0, 3.0, 6.0])], groups=True))
    objects = RandomUrdfObjectSet(folder)
    split, whole, broken = objects.load(0), objects.load(1), objects.load(2)
    assert broken is None
    assert len(split.shapes) == 2 and split.color[:3] == (0.1, 0.2, 0.3)
    assert len(whole.shapes) >= 2, "one non-convex group is decomposed with CoACD"
    assert any((tmp_path / "cache" / "coacd").iterdir())
    # Standing on the tallest stable side: the ring lies flat, the tall box stands.
    assert np.argmin(whole.collision_mesh().extents) == 2
    assert np.argmax(objects.load(3).collision_mesh().extents) == 2
    for obj in (split, whole):
        _check_graspable_convex_union(obj)
    # Cached on disk: a fresh set reads the same parts back.
    again = RandomUrdfObjectSet(folder).load(0)
    for sa, sb in zip(split.shapes, again.shapes):
        np.testing.assert_allclose(sa.vertices, sb.vertices)
    rng = np.random.default_rng(0)
    assert {objects.sample(rng).name for _ in range(10)} <= {"urdf000", "urdf001", "urdf003"}


@pytest.mark.sim
def test_grasp_clutter_with_random_urdfs_is_seeded_and_has_grasps():
    env = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_ee_twist", num_points=256,
                   object_source="random_urdfs", scene_type="mixed")
    try:
        runs = []
        for seed in (3, 4, 3):
            obs, _ = env.reset(seed=seed)
            layout = env.unwrapped.layouts[0]
            assert layout.objects and all(o.name.startswith("urdf") for o in layout.objects)
            assert int(obs["extra"]["grasps_mask"][0].sum()) >= 1
            runs.append(([o.name for o in layout.objects], layout.object_poses.copy(),
                         obs["extra"]["grasps"][0].clone()))
        assert runs[0][0] == runs[2][0]
        np.testing.assert_allclose(runs[0][1], runs[2][1], atol=1e-6)
        assert bool((runs[0][2] == runs[2][2]).all())
        assert runs[0][0] != runs[1][0] or not np.allclose(runs[0][1], runs[1][1])
    finally:
        env.close()


def test_benchmark_shared_takes_the_object_source(tmp_path):
    import argparse

    from rtv3_maniskill.benchmarks.shared_config import BenchmarkConfig
    from rtv3_maniskill.cli.benchmark_shared import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    from rtv3_maniskill.cli.scene_args import scene_settings

    assert scene_settings(parser.parse_args(["--objects", "random_urdfs"]))["object_source"] == "random_urdfs"
    assert scene_settings(parser.parse_args([]))["object_source"] == "procedural"  # the easy preset's
    assert scene_settings(parser.parse_args(["--preset", "paper"]))["object_source"] == "ycb"
    default = BenchmarkConfig(output=tmp_path, methods=["direct"], users=["noisy"])
    urdfs = BenchmarkConfig(output=tmp_path, methods=["direct"], users=["noisy"], object_source="random_urdfs")
    assert default.fingerprint(None)["object_source"] == "procedural"
    assert urdfs.fingerprint(None)["object_source"] == "random_urdfs"
