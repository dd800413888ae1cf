"""Grasp candidates for clutter scenes: geometry, hand collision, determinism, API."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pinocchio as pin
import pytest
import torch
import trimesh
from scipy.spatial import ConvexHull

from rtv3_maniskill.robot.panda_hand import (
    FINGER_Z_IN_TCP,
    MAX_OPENING,
    TCP_OFFSET,
    hand_parts,
    panda_asset_dir,
)
from rtv3_maniskill.robot.scene_geometry import (
    WORKSPACE_CENTER,
    WORKSPACE_HALF_SIZE,
    CollisionShape,
    ObjectGeometry,
    SceneGeometry,
)
from rtv3_maniskill.se3 import quat_to_matrix
from rtv3_maniskill.tasks.antipodal_grasps import FRICTION_COEFFICIENT
from rtv3_maniskill.tasks.grasp_sampler import canonicalize_symmetric, sample_grasps
from rtv3_maniskill.tasks.grasp_set import GraspSet

CONE = math.atan(FRICTION_COEFFICIENT)
CLEARANCE = 0.01  # sample_grasps' default finger_clearance


# --------------------------------------------------------------------------- scenes


def _object(name: str, shape: CollisionShape) -> ObjectGeometry:
    return ObjectGeometry(name, [shape], shape.to_trimesh())


def _pose(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    pose = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])
    pose[:3, 3] = [x, y, z]
    return pose


def _clutter_scene() -> SceneGeometry:
    """A standing 4x4x8 cm box, a lying cylinder r=3 cm, a sphere r=3 cm, a few cm apart."""
    objects = [
        _object("box", CollisionShape("box", (0.02, 0.02, 0.04))),
        _object("cylinder", CollisionShape("cylinder", (0.03, 0.05))),  # axis = local x, lying
        _object("sphere", CollisionShape("sphere", (0.03,))),
    ]
    poses = np.stack([_pose(-0.09, -0.07, 0.04, 0.3), _pose(0.0, 0.01, 0.03, 0.7), _pose(-0.1, 0.06, 0.03)])
    return SceneGeometry(objects, poses)


def _single(shape: CollisionShape, pose: np.ndarray) -> SceneGeometry:
    return SceneGeometry([_object("o", shape)], pose[None])


@pytest.fixture(scope="module")
def clutter() -> tuple[SceneGeometry, GraspSet]:
    scene = _clutter_scene()
    return scene, sample_grasps(scene, np.random.default_rng(0))


# --------------------------------------------------------------- independent hand model


@lru_cache(maxsize=1)
def _urdf_hand():
    """Pinocchio model of panda_v2.urdf with the collision geometry of link7, hand, fingers.

    For each geometry: surface points and hull half-spaces ``(F, 4)`` in its own frame.
    """
    urdf = str(panda_asset_dir() / "panda_v2.urdf")
    model = pin.buildModelFromUrdf(urdf)
    geom = pin.buildGeomFromUrdf(model, urdf, pin.GeometryType.COLLISION, package_dirs=[str(panda_asset_dir())])
    rng = np.random.default_rng(123)
    entries = []
    for i, go in enumerate(geom.geometryObjects):
        frame = model.frames[go.parentFrame].name
        if frame not in ("panda_link7", "panda_hand", "panda_leftfinger", "panda_rightfinger"):
            continue
        if hasattr(go.geometry, "halfSide"):
            mesh = trimesh.creation.box(extents=2 * np.asarray(go.geometry.halfSide))
        else:
            mesh = trimesh.load(go.meshPath, force="mesh")
        count = int(mesh.area / 1.5e-3**2)  # one point per ~1.5 x 1.5 mm
        points = np.concatenate([mesh.vertices, trimesh.sample.sample_surface(mesh, count, seed=rng)[0]])
        hull = ConvexHull(mesh.vertices)
        entries.append((i, frame, points, hull.equations))
    return model, geom, entries


def _hand_placements(opening: float) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(frame, tcp_from_geom (4,4), points, equations)`` with both fingers at ``opening / 2``."""
    model, geom, entries = _urdf_hand()
    data, gdata = model.createData(), geom.createData()
    q = pin.neutral(model)
    q[model.joints[model.getJointId("panda_finger_joint1")].idx_q] = opening / 2
    q[model.joints[model.getJointId("panda_finger_joint2")].idx_q] = opening / 2
    pin.framesForwardKinematics(model, data, q)
    pin.updateGeometryPlacements(model, data, geom, gdata)
    tcp_inv = data.oMf[model.getFrameId("panda_hand_tcp")].inverse()
    return [(frame, (tcp_inv * gdata.oMg[i]).homogeneous, pts, eq) for i, frame, pts, eq in entries]


def _object_hulls(scene: SceneGeometry):
    """Per object part: hull equations (F, 4), bounding sphere, surface points (world)."""
    rng = np.random.default_rng(7)
    out = []
    for k, (obj, pose) in enumerate(zip(scene.objects, scene.object_poses)):
        for shape in obj.shapes:
            mesh = shape.to_trimesh()
            mesh.apply_transform(pose)
            centre = mesh.vertices.mean(0)
            radius = np.linalg.norm(mesh.vertices - centre, axis=1).max()
            points = np.concatenate([mesh.vertices, trimesh.sample.sample_surface(mesh, 3000, seed=rng)[0]])
            out.append((k, ConvexHull(mesh.vertices).equations, centre, radius, points))
    return out


def _penetration(points: np.ndarray, equations: np.ndarray) -> np.ndarray:
    """Depth (m) by which each point lies inside a convex hull (<= 0 when outside)."""
    return -(points @ equations[:, :3].T + equations[:, 3]).max(1)


def _hand_intrusions(scene: SceneGeometry, tcp_pose: np.ndarray, opening: float) -> list[str]:
    """Names of what the URDF hand at ``tcp_pose`` with ``opening`` penetrates (> 0.1 mm)."""
    hits = []
    hulls = _object_hulls_cached(id(scene), scene)
    table_top = scene.table_center[2] + scene.table_half_size[2]
    for frame, tcp_from_geom, pts, eq in _hand_placements(opening):
        world_from_geom = tcp_pose @ tcp_from_geom
        world_pts = pts @ world_from_geom[:3, :3].T + world_from_geom[:3, 3]
        if world_pts[:, 2].min() < table_top - 1e-4:
            hits.append(f"{frame} below the table")
        geom_centre = world_pts.mean(0)
        geom_radius = np.linalg.norm(world_pts - geom_centre, axis=1).max()
        geom_from_world = np.linalg.inv(world_from_geom)
        for k, obj_eq, centre, radius, obj_pts in hulls:
            if np.linalg.norm(centre - geom_centre) > radius + geom_radius:
                continue
            if (_penetration(world_pts, obj_eq) > 1e-4).any():
                hits.append(f"{frame} in object {k}")
            local = obj_pts @ geom_from_world[:3, :3].T + geom_from_world[:3, 3]
            if (_penetration(local, eq) > 1e-4).any():
                hits.append(f"object {k} in {frame}")
    return hits


_HULL_CACHE: dict[int, list] = {}


def _object_hulls_cached(key: int, scene: SceneGeometry):
    if key not in _HULL_CACHE:
        _HULL_CACHE[key] = _object_hulls(scene)
    return _HULL_CACHE[key]


# --------------------------------------------------------------------------- TCP frame


def test_tcp_convention_matches_urdf_and_maniskill():
    model, _, _ = _urdf_hand()
    data = model.createData()
    q = pin.neutral(model)
    q[model.joints[model.getJointId("panda_finger_joint1")].idx_q] = 0.03
    q[model.joints[model.getJointId("panda_finger_joint2")].idx_q] = 0.03
    pin.framesForwardKinematics(model, data, q)
    tcp = data.oMf[model.getFrameId("panda_hand_tcp")]

    def in_tcp(name: str) -> np.ndarray:
        return (tcp.inverse() * data.oMf[model.getFrameId(name)]).homogeneous

    np.testing.assert_allclose(in_tcp("panda_hand")[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(in_tcp("panda_hand")[:3, 3], [0, 0, -TCP_OFFSET], atol=1e-12)
    # Pads sit at y = +-q around the TCP origin: y is the closing axis, left finger at +y.
    np.testing.assert_allclose(in_tcp("panda_leftfinger_pad")[:3, 3], [0, 0.03, 0.0005], atol=1e-9)
    np.testing.assert_allclose(in_tcp("panda_rightfinger_pad")[:3, 3], [0, -0.03, 0.0005], atol=1e-9)
    np.testing.assert_allclose(in_tcp("panda_leftfinger")[:3, 3], [0, 0.03, FINGER_Z_IN_TCP], atol=1e-9)

    from mani_skill.agents.robots.panda.panda import Panda

    approach, closing, centre = np.array([0.0, 0.6, -0.8]), np.array([1.0, 0.0, 0.0]), np.array([0.1, 0.0, 0.05])
    built = Panda.build_grasp_pose(approach, closing, centre).to_transformation_matrix()
    np.testing.assert_allclose(built[:3, 2], approach, atol=1e-6)  # z = approach
    np.testing.assert_allclose(built[:3, 1], closing, atol=1e-6)  # y = closing
    np.testing.assert_allclose(built[:3, 0], np.cross(closing, approach), atol=1e-6)


@pytest.mark.parametrize("opening", [0.0, 0.05, MAX_OPENING])
def test_hand_parts_cover_the_urdf_collision_geometry(opening):
    parts = {p.name: p for p in hand_parts(0.0)}
    owner = {"panda_link7": "wrist", "panda_hand": "palm", "panda_leftfinger": "left_finger",
             "panda_rightfinger": "right_finger"}
    for frame, tcp_from_geom, pts, _ in _hand_placements(opening):
        part = parts[owner[frame]]
        local = pts @ tcp_from_geom[:3, :3].T + tcp_from_geom[:3, 3] - part.offset(np.array(opening))
        eq = ConvexHull(part.vertices).equations
        assert _penetration(local, eq).min() > -1e-6, f"{frame} sticks out of the {part.name} model"


# --------------------------------------------------------------------------- sampling


def test_grasps_found_on_every_object(clutter):
    scene, grasps = clutter
    assert 0 < len(grasps) <= 64
    assert set(grasps.object_ids.tolist()) == {0, 1, 2}
    assert grasps.poses.shape == (len(grasps), 4, 4) and grasps.object_ids.dtype == np.int64


def test_grasps_are_valid_frames_in_range(clutter):
    _, g = clutter
    rot = g.poses[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    assert ((g.widths > 0) & (g.widths <= MAX_OPENING)).all()
    assert ((g.scores > 0.4) & (g.scores <= 1.0)).all()
    lo = WORKSPACE_CENTER - WORKSPACE_HALF_SIZE - 0.03
    hi = WORKSPACE_CENTER + WORKSPACE_HALF_SIZE + 0.03
    assert ((g.poses[:, :3, 3] >= lo) & (g.poses[:, :3, 3] <= hi)).all()
    assert (g.poses[:, 2, 2] <= 0.5).all()  # never approaching steeply from below


def test_contacts_are_antipodal_on_the_object_surface(clutter):
    scene, g = clutter
    hulls = {k: eq for k, eq, *_ in _object_hulls(scene)}
    for pose, width, k in zip(g.poses, g.widths, g.object_ids):
        y = pose[:3, 1]
        for side in (1.0, -1.0):
            contact = pose[:3, 3] + side * width / 2 * y
            signed = hulls[k][:, :3] @ contact + hulls[k][:, 3]
            assert abs(signed.max()) < 1e-6, "contact point is not on the object's surface (TCP not centred)"
            normal = hulls[k][signed.argmax(), :3]
            assert np.arccos(np.clip(normal @ (side * y), -1, 1)) <= CONE + 1e-6


def test_grasps_are_collision_free_under_a_dense_independent_check(clutter):
    """URDF hand (pinocchio geometry), fingers opened as the sampler assumes, at the grasp,
    halfway and at the pre-grasp: no point of the hand inside any object or the table, no
    object point inside any hand part."""
    scene, g = clutter
    pregrasps = g.pregrasp_poses()
    for i in range(len(g)):
        opening = min(g.widths[i] + 2 * CLEARANCE, MAX_OPENING)
        for pose in (g.poses[i], (g.poses[i] + pregrasps[i]) / 2, pregrasps[i]):
            hits = _hand_intrusions(scene, pose, opening)
            assert not hits, f"grasp {i} on object {g.object_ids[i]}: {hits}"


def test_dense_check_detects_a_colliding_hand(clutter):
    """The independent check used above is able to fail."""
    scene, g = clutter
    for i in range(0, len(g), 5):
        # Jaw closed on the object: the pads would sit inside it (the TCP is between contacts).
        assert any("finger in object" in hit for hit in _hand_intrusions(scene, g.poses[i], 0.0))
    pose = g.poses[0].copy()
    pose[:3, 3] += 0.08 * pose[:3, 2]  # palm (3.7..12.9 cm behind the TCP) now spans the old TCP
    assert any("panda_hand" in hit for hit in _hand_intrusions(scene, pose, 0.08))


def test_non_maximum_suppression_keeps_candidates_diverse(clutter):
    _, g = clutter
    for k in np.unique(g.object_ids):
        poses = g.poses[g.object_ids == k]
        for a in range(len(poses)):
            for b in range(a + 1, len(poses)):
                rel = poses[a, :3, :3].T @ poses[b, :3, :3]
                angle = min(
                    np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)),
                    np.arccos(np.clip((np.trace(rel @ np.diag([-1, -1, 1])) - 1) / 2, -1, 1)),
                )
                near = np.linalg.norm(poses[a, :3, 3] - poses[b, :3, 3]) < 0.015
                assert not (near and angle < math.radians(20))


def test_same_seed_gives_identical_grasps_and_other_seeds_differ():
    scene = _clutter_scene()
    a = sample_grasps(scene, np.random.default_rng(5), max_grasps=16)
    b = sample_grasps(scene, np.random.default_rng(5), max_grasps=16)
    c = sample_grasps(scene, np.random.default_rng(6), max_grasps=16)
    for name in ("poses", "widths", "scores", "object_ids"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len(a) <= 16
    assert len(a) != len(c) or not np.array_equal(a.poses, c.poses)


def test_max_grasps_caps_and_spreads_over_objects():
    grasps = sample_grasps(_clutter_scene(), np.random.default_rng(1), max_grasps=3)
    assert len(grasps) == 3
    assert sorted(grasps.object_ids.tolist()) == [0, 1, 2]  # round-robin: one per object first


def test_pregrasp_is_five_cm_back_along_the_approach(clutter):
    _, g = clutter
    pre = g.pregrasp_poses()
    back = np.eye(4)
    back[2, 3] = -0.05
    np.testing.assert_allclose(pre, g.poses @ back, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pre[:, :3, 3] - g.poses[:, :3, 3], axis=1), 0.05, atol=1e-12)
    np.testing.assert_allclose(g.pregrasp_poses(0.1)[:, :3, :3], g.poses[:, :3, :3])


def test_multi_part_object_contacts_lie_on_the_union_surface():
    """A hammer-like object from two overlapping boxes: contacts on the outer surface of the
    union, hand free of both parts."""
    handle = CollisionShape("box", (0.07, 0.012, 0.012))
    head = CollisionShape("box", (0.015, 0.035, 0.015), local_pose=_pose(0.06, 0.0, 0.003))
    obj = ObjectGeometry("hammer", [handle, head], trimesh.util.concatenate([handle.to_trimesh(), head.to_trimesh()]))
    scene = SceneGeometry([obj], _pose(-0.05, 0.0, 0.012, 0.5)[None])
    g = sample_grasps(scene, np.random.default_rng(3), num_surface_samples=192)
    assert len(g) >= 3
    parts = [eq for _, eq, *_ in _object_hulls(scene)]
    for pose, width in zip(g.poses, g.widths):
        for side in (1.0, -1.0):
            contact = pose[:3, 3] + side * width / 2 * pose[:3, 1]
            # On the union's surface: on the boundary of one part, inside none.
            signed = [(eq[:, :3] @ contact + eq[:, 3]).max() for eq in parts]
            assert abs(min(signed)) < 1e-6
        opening = min(width + 2 * CLEARANCE, MAX_OPENING)
        assert not _hand_intrusions(scene, pose, opening)


def test_plate_wider_than_the_gripper_has_no_grasp():
    """12 x 12 x 4 cm: the only dimension under 8 cm is vertical, and closing on it needs a
    finger under the plate (table); across a corner the normals are 45 deg off the jaw."""
    plate = _single(CollisionShape("box", (0.06, 0.06, 0.02)), _pose(-0.05, 0.0, 0.02, 0.4))
    grasps = sample_grasps(plate, np.random.default_rng(0), num_surface_samples=256)
    assert len(grasps) == 0


def test_long_bar_is_grasped_only_across_its_narrow_side():
    yaw = 0.4
    bar = _single(CollisionShape("box", (0.06, 0.025, 0.025)), _pose(-0.05, 0.0, 0.025, yaw))
    grasps = sample_grasps(bar, np.random.default_rng(0), num_surface_samples=256)
    assert len(grasps) >= 3
    long_axis = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    closing = grasps.poses[:, :3, 1]
    assert (np.abs(closing @ long_axis) <= math.sin(CONE) + 1e-9).all()
    short_axis = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    np.testing.assert_allclose(grasps.widths, 0.05 / np.abs(closing @ short_axis), atol=1e-6)
    # Closing vertically would put a finger into the table: every jaw is close to horizontal.
    assert (np.abs(closing[:, 2]) <= math.sin(CONE) + 1e-9).all()


def test_empty_scene_gives_empty_set():
    grasps = sample_grasps(SceneGeometry([], np.zeros((0, 4, 4))), np.random.default_rng(0))
    assert len(grasps) == 0 and grasps.poses.shape == (0, 4, 4)
    rows, mask = grasps.to_padded(4)
    assert rows.shape == (4, 9) and not rows.any() and not mask.any()


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"max_grasps": 0}, "max_grasps"),
        ({"max_grasps": -3}, "max_grasps"),
        ({"num_surface_samples": 0}, "num_surface_samples"),
        ({"finger_clearance": float("nan")}, "finger_clearance"),
    ],
)
def test_bad_arguments_are_rejected(kwargs, word):
    with pytest.raises(ValueError, match=word):
        sample_grasps(_clutter_scene(), np.random.default_rng(0), **kwargs)


def test_bad_scene_and_rng_are_rejected():
    scene = _clutter_scene()
    scene.object_poses = scene.object_poses[:2]
    with pytest.raises(ValueError, match="object_poses"):
        sample_grasps(scene, np.random.default_rng(0))
    scene = _clutter_scene()
    scene.object_poses[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        sample_grasps(scene, np.random.default_rng(0))
    with pytest.raises(TypeError, match="rng"):
        sample_grasps(_clutter_scene(), 0)


# --------------------------------------------------------------------------- GraspSet API


def test_to_padded_matches_the_feature_layout(clutter):
    _, g = clutter
    rows, mask = g.to_padded(64)
    m = len(g)
    assert rows.dtype == np.float32 and mask.dtype == np.float32 and rows.shape == (64, 9)
    np.testing.assert_array_equal(mask, np.r_[np.ones(m), np.zeros(64 - m)])
    np.testing.assert_allclose(rows[:m, :3], g.poses[:, :3, 3], atol=1e-6)
    rot = quat_to_matrix(torch.from_numpy(rows[:m, 3:7].astype(np.float64))).numpy()
    np.testing.assert_allclose(rot, g.poses[:, :3, :3], atol=1e-6)
    assert (rows[:m, 3] >= 0).all()  # w >= 0
    np.testing.assert_allclose(rows[:m, 7], g.widths, atol=1e-7)
    np.testing.assert_allclose(rows[:m, 8], g.scores, atol=1e-7)
    assert not rows[m:].any()
    with pytest.raises(ValueError, match="max_grasps"):
        g.to_padded(m - 1)
    with pytest.raises(ValueError, match="max_grasps"):
        g.to_padded(0)


def test_grasp_set_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="widths"):
        GraspSet(np.tile(np.eye(4), (2, 1, 1)), np.zeros(3), np.zeros(2), np.zeros(2))


def test_canonicalize_symmetric_picks_the_variant_closer_to_the_reference():
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (50, 1, 1))
    poses[:, :3, :3] = trimesh.transformations.random_rotation_matrix(rng.random((3,)))[:3, :3]
    for i in range(50):
        poses[i, :3, :3] = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
        poses[i, :3, 3] = rng.normal(size=3)
    reference = np.eye(4)
    reference[:3, :3] = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    out = canonicalize_symmetric(poses, reference)
    flip = np.diag([-1.0, -1.0, 1.0])

    def angle(r):
        return np.arccos(np.clip((np.trace(reference[:3, :3].T @ r) - 1) / 2, -1, 1))

    for before, after in zip(poses, out):
        np.testing.assert_allclose(after[:, 2:], before[:, 2:])  # approach and position kept
        other = after[:3, :3] @ flip
        assert np.allclose(after[:3, :3], before[:3, :3]) or np.allclose(after[:3, :3], before[:3, :3] @ flip)
        assert angle(after[:3, :3]) <= angle(other) + 1e-9
    np.testing.assert_allclose(canonicalize_symmetric(out, reference), out)
    with pytest.raises(ValueError, match="grasp_poses"):
        canonicalize_symmetric(np.eye(4), reference)
