"""The project's one SE(3) module, checked once."""

import math

import torch

from rtv3_maniskill import se3


def _random_twists(n: int, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=gen, dtype=torch.float64)
    xi[:, 3:] *= 0.9  # rotation angles below pi
    return xi


def test_exp_log_round_trip_and_small_angles():
    xi = _random_twists(64)
    torch.testing.assert_close(se3.se3_log(se3.se3_exp(xi)), xi)
    tiny = torch.tensor([[1e-3, -2e-3, 5e-4, 1e-7, -2e-7, 3e-7]], dtype=torch.float64)
    torch.testing.assert_close(se3.se3_log(se3.se3_exp(tiny)), tiny)


def test_quaternion_round_trip_and_rotation_validity():
    rot = se3.se3_exp(_random_twists(32, 1))[:, :3, :3]
    torch.testing.assert_close(se3.quat_to_matrix(se3.matrix_to_quat(rot)), rot)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=rot.dtype).expand_as(rot))


def test_adjoint_maps_body_twists_between_frames():
    xi = _random_twists(8, 2)
    t_ab = se3.se3_exp(_random_twists(8, 3))
    # exp(Ad_T xi) = T exp(xi) T^-1
    lhs = se3.se3_exp((se3.adjoint(t_ab) @ xi[..., None])[..., 0])
    rhs = t_ab @ se3.se3_exp(xi) @ se3.se3_inverse(t_ab)
    torch.testing.assert_close(lhs, rhs)


def test_integration_and_body_twist_agree():
    start = se3.se3_exp(_random_twists(1, 4))[0]
    twists = _random_twists(5, 5) * 0.2
    poses = se3.integrate_body_twists(start, twists, 0.05)
    torch.testing.assert_close(se3.body_twist(start, poses[0], 0.05), twists[0])
    torch.testing.assert_close(se3.body_twist(poses[3], poses[4], 0.05), twists[4])


def test_translate_along_z_is_the_pregrasp_offset():
    grasp = se3.se3_exp(_random_twists(4, 6))
    pre = se3.translate_along_z(grasp, -0.05)
    torch.testing.assert_close(se3.relative_transform(grasp, pre)[:, :3, 3],
                               torch.tensor([[0.0, 0.0, -0.05]] * 4, dtype=grasp.dtype))
    torch.testing.assert_close(pre[:, :3, :3], grasp[:, :3, :3])


def test_pose_distance_and_its_gripper_symmetric_version():
    pose = se3.se3_exp(_random_twists(3, 7))
    assert torch.allclose(se3.pose_distance(pose, pose), torch.zeros(3, dtype=pose.dtype), atol=1e-9)
    shifted = se3.translate_along_z(pose, 0.01)
    torch.testing.assert_close(se3.pose_distance(pose, shifted), torch.full((3,), 0.01, dtype=pose.dtype))
    twin = se3.rotate_about_z(pose, math.pi)
    assert (se3.pose_distance(pose, twin, 0.3 / math.pi) > 0.29).all()
    assert torch.allclose(se3.symmetric_pose_distance(pose, twin, 0.3 / math.pi), torch.zeros(3, dtype=pose.dtype),
                          atol=1e-7)


def test_half_turn_about_z_is_exact_and_matches_the_general_rotation():
    pose = se3.se3_exp(_random_twists(5, 8))
    twin = se3.rotate_about_z(pose, math.pi)
    torch.testing.assert_close(twin, se3.rotate_about_z(pose, math.pi - 1e-9), atol=1e-8, rtol=0)
    torch.testing.assert_close(se3.relative_transform(pose, twin)[:, :3, :3],
                               torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=pose.dtype)).expand(5, 3, 3))
    assert torch.equal(se3.rotate_about_z(twin, math.pi), pose)  # the twin of the twin is the grasp, bit for bit
    assert torch.equal(twin[:, :3, 3], pose[:, :3, 3])


def test_functions_first_called_in_inference_mode_still_train():
    """Constants converted on a first call under ``torch.inference_mode`` are reused by later
    training steps; they must be ordinary tensors that autograd may save."""
    se3._CONSTANTS.clear()  # make this the first float32 call of the process
    w = torch.randn(4, 3, dtype=torch.float32)
    with torch.inference_mode():
        expected = se3.se3_log(se3.se3_exp(torch.cat([w, w], -1)))
    xi = torch.cat([w, w], -1).requires_grad_(True)
    out = se3.se3_log(se3.se3_exp(xi))
    out.sum().backward()
    torch.testing.assert_close(out.detach(), expected)
    assert xi.grad is not None and bool(torch.isfinite(xi.grad).all())
