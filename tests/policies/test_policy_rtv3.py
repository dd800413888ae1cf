"""Tests of the RT-V3 prior as a LeRobot policy (rtv3_maniskill/policies/rtv3).

Batches are synthetic but physically plausible: a box on a table seen as a point cloud,
top-down grasp candidates on the box, and an end effector that moved along a constant body
twist (a straight SE(3) line) towards the pre-grasp of one of them.
"""

from __future__ import annotations

import math

import pytest
import torch

from rtv3_maniskill import features as ft
from rtv3_maniskill import se3
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
from rtv3_maniskill.policies.rtv3.constants import GRASP_FEATURE_DIM
from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy
from rtv3_maniskill.policies.rtv3.point_encoder import (
    GridPooling,
    PointTransformerEncoder,
    _spread_bits,
    morton_code,
    serial_key,
)
from rtv3_maniskill.twist_mixture import TwistMixture

SMALL = dict(num_points=256, max_grasps=16)
REACH_STEPS = 20  # the synthetic user reaches the pre-grasp in 1 s


# ----------------------------------------------------------------------------- synthetic scenes


def _rot_x(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def make_scene_batch(
    cfg: RTV3Config, batch: int = 3, seed: int = 0, grasps_valid: int | None = None, box_spread: float = 0.05
) -> dict:
    """Dataset-like batch: ``state (B, T, 27)``, context with a time axis, ``action (B, H, 6)``.

    ``box_spread``: standard deviation (m) of the box position on the table.
    """
    g = torch.Generator().manual_seed(seed)
    t_hist, horizon, n, m = cfg.n_obs_steps, cfg.horizon, cfg.num_points, cfg.max_grasps
    down = _rot_x(math.pi)  # gripper z axis pointing down
    center = torch.tensor([0.5, 0.0, 0.05]) + torch.cat([box_spread * torch.randn(batch, 2, generator=g),
                                                         torch.zeros(batch, 1)], 1)
    half = torch.tensor([0.05, 0.03, 0.05])

    # Point cloud: half on the table, half on the box surface; the rest padding for sample 0.
    n_table = n // 2
    table = torch.rand(batch, n_table, 3, generator=g) * torch.tensor([0.6, 0.6, 0.0]) + torch.tensor([0.2, -0.3, 0.0])
    box = (torch.rand(batch, n - n_table, 3, generator=g) * 2 - 1) * half
    face = torch.randint(0, 3, (batch, n - n_table), generator=g)
    sign = torch.where(torch.rand(batch, n - n_table, generator=g) < 0.5, -1.0, 1.0)
    box = box.scatter(2, face[..., None], (sign * half[face])[..., None]) + center[:, None]
    xyz = torch.cat([table, box], 1)
    cloud = torch.cat([xyz, torch.rand(batch, n, 3, generator=g)], -1)
    cloud_mask = torch.ones(batch, n)
    cloud_mask[0, -n // 8 :] = 0.0
    cloud[0, -n // 8 :] = 0.0

    # Grasps: top-down on the box top with random yaw.
    yaw = torch.rand(batch, m, generator=g) * math.pi
    rot = down @ se3.so3_exp(torch.stack([torch.zeros_like(yaw), torch.zeros_like(yaw), yaw], -1))
    pos = center[:, None] + torch.cat([0.02 * torch.randn(batch, m, 2, generator=g),
                                       torch.full((batch, m, 1), 0.04)], -1)
    grasp_pose = se3.make_transform(rot, pos)
    grasps = torch.cat([se3.matrix_to_pose(grasp_pose), torch.full((batch, m, 1), 0.05),
                        0.5 + 0.5 * torch.rand(batch, m, 1, generator=g)], -1)
    n_valid = m if grasps_valid is None else grasps_valid
    grasp_mask = torch.zeros(batch, m)
    grasp_mask[:, :n_valid] = 1.0
    grasps = grasps * grasp_mask[..., None]

    # Straight SE(3) line from a random start to the pre-grasp of grasp 0 (5 cm back along its z axis).
    back = se3.make_transform(torch.eye(3), torch.tensor([0.0, 0.0, -0.05]))
    pre_grasp = grasp_pose[:, 0] @ back
    start_rot = down @ se3.so3_exp(0.3 * torch.randn(batch, 3, generator=g))
    start = se3.make_transform(start_rot, torch.tensor([0.4, 0.0, 0.35]) + 0.05 * torch.randn(batch, 3, generator=g))
    twist = se3.se3_log(se3.relative_transform(start, pre_grasp)) / (REACH_STEPS * ft.DT)  # (B, 6) body twist
    steps = torch.arange(t_hist + horizon, dtype=torch.float32)
    poses = start[:, None] @ se3.se3_exp(twist[:, None] * ft.DT * steps[None, :, None])
    state = torch.zeros(batch, t_hist, ft.STATE_DIM)
    state[..., 0:7] = se3.matrix_to_pose(poses[:, :t_hist])
    state[..., ft.EE_TWIST] = twist[:, None]
    state[..., ft.ARM_QPOS] = 0.1 * torch.randn(batch, t_hist, 7, generator=g)
    moving = (t_hist - 1 + torch.arange(horizon)) < REACH_STEPS
    action = twist[:, None] * moving[None, :, None]

    def with_time(x: torch.Tensor) -> torch.Tensor:
        return x[:, None].expand(batch, t_hist, *x.shape[1:]).clone()

    return {
        ft.STATE: state,
        ft.POINT_CLOUD: with_time(cloud),
        ft.POINT_CLOUD_MASK: with_time(cloud_mask),
        ft.GRASPS: with_time(grasps),
        ft.GRASPS_MASK: with_time(grasp_mask),
        ft.ACTION: action,
        f"{ft.ACTION}_is_pad": torch.zeros(batch, horizon, dtype=torch.bool),
        f"{ft.STATE}_is_pad": torch.zeros(batch, t_hist, dtype=torch.bool),
    }


def observation_only(batch: dict) -> dict:
    return {k: v for k, v in batch.items() if k.startswith("observation.") and not k.endswith("_is_pad")}


def transform_world(batch: dict, transform: torch.Tensor) -> dict:
    """Apply one rigid transform ``(4, 4)`` to every world-frame input (states, points, grasps)."""
    out = dict(batch)
    state = batch[ft.STATE].clone()
    pose = se3.pose_to_matrix(state[..., 0:3], state[..., 3:7])
    state[..., 0:7] = se3.matrix_to_pose(transform @ pose)  # body twists are frame-invariant
    out[ft.STATE] = state
    cloud = batch[ft.POINT_CLOUD].clone()
    cloud[..., :3] = cloud[..., :3] @ transform[:3, :3].T + transform[:3, 3]
    out[ft.POINT_CLOUD] = cloud * (batch[ft.POINT_CLOUD_MASK][..., None] > 0)
    grasps = batch[ft.GRASPS].clone()
    gpose = se3.pose_to_matrix(grasps[..., 0:3], grasps[..., 3:7])
    grasps[..., 0:7] = se3.matrix_to_pose(transform @ gpose)
    out[ft.GRASPS] = grasps * (batch[ft.GRASPS_MASK][..., None] > 0)
    return out


def make_policy(seed: int = 0, **overrides) -> RTV3Policy:
    torch.manual_seed(seed)
    cfg = RTV3Config(device="cpu", **{**SMALL, **overrides})
    return RTV3Policy(cfg)


@pytest.fixture(scope="module")
def policy() -> RTV3Policy:
    return make_policy().eval()


@pytest.fixture(scope="module")
def batch(policy: RTV3Policy) -> dict:
    return make_scene_batch(policy.config, batch=3, seed=1)


# ----------------------------------------------------------------------------- config


def test_config_windows_presets_and_validation():
    cfg = RTV3Config(device="cpu")
    # one row per sample: the history is observation.state_history or, like the future actions, cut
    # from the training cache (training_cache.py)
    assert cfg.observation_delta_indices is None and cfg.action_delta_indices is None
    assert cfg.reward_delta_indices is None
    assert cfg.kl_weight == 100.0 and cfg.num_maneuver_classes == 10
    optimizer = cfg.get_optimizer_preset()
    assert optimizer.lr == 1e-3 and optimizer.grad_clip_norm == 1.0
    # the fused Adam of the preset takes LeRobot's (plain) Adam steps
    weights = [torch.randn(5, 3, requires_grad=True) for _ in range(2)]
    plain = [w.detach().clone().requires_grad_() for w in weights]
    fused_opt, plain_opt = optimizer.build(weights), torch.optim.Adam(plain, lr=1e-3)
    assert fused_opt.defaults["fused"] is True
    for step in range(3):
        for ws, opt in ((weights, fused_opt), (plain, plain_opt)):
            opt.zero_grad()
            sum(((w - step) ** 2).sum() for w in ws).backward()
            opt.step()
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(weights, plain))
    scheduler = cfg.get_scheduler_preset().build(torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=1e-3), 10)
    assert scheduler.lr_lambdas[0](0) == 1.0 and scheduler.lr_lambdas[0](10**6) == pytest.approx(0.1)
    with pytest.raises(ValueError, match="num_maneuver_classes"):
        RTV3Config(device="cpu", num_maneuver_classes=0)
    with pytest.raises(ValueError, match="rotation_conditioning"):
        RTV3Config(device="cpu", rotation_conditioning="mean")
    with pytest.raises(ValueError, match="twist_noise_angular"):
        RTV3Config(device="cpu", twist_noise_angular=-0.1)
    with pytest.raises(ValueError, match="n_action_steps"):
        RTV3Config(device="cpu", n_action_steps=13)
    with pytest.raises(ValueError, match="heads"):
        RTV3Config(device="cpu", grasp_dim=30)
    with pytest.raises(ValueError, match="history_rotation_resample_prob"):
        RTV3Config(device="cpu", history_rotation_resample_prob=1.5)
    with pytest.raises(ValueError, match="optimizer_min_lr"):
        RTV3Config(device="cpu", optimizer_min_lr=1e-2)


def test_feature_validation_names_the_problem():
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = RTV3Config(device="cpu", **SMALL)
    cfg.input_features = cfg.default_input_features()
    cfg.output_features = cfg.default_output_features()
    cfg.validate_features()
    cfg.input_features[ft.STATE] = PolicyFeature(FeatureType.STATE, (20,))
    with pytest.raises(ValueError, match="observation.state"):
        cfg.validate_features()
    cfg.input_features = {ft.STATE: PolicyFeature(FeatureType.STATE, (27,))}
    with pytest.raises(ValueError, match="scene context"):
        cfg.validate_features()
    cfg.input_features["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (123,))
    with pytest.raises(ValueError, match="environment_state_dim"):
        cfg.validate_features()


def test_morton_code_interleaves_bits():
    x = torch.randint(0, 1 << 16, (200,))
    naive = [sum(((v >> b) & 1) << (3 * b) for b in range(16)) for v in x.tolist()]
    assert _spread_bits(x).tolist() == naive
    grid = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    assert morton_code(grid).tolist() == [1, 2, 4, 7]
    assert morton_code(grid, "z-trans").tolist() == [2, 1, 4, 7]


def test_grid_pooling_of_a_z_ordered_list_needs_no_sort():
    # A list serialised along z is pooled without sorting (halving the grid drops the low bits of
    # the code); that must equal pooling the same list as if its order were unknown, and the
    # pooled list must come out sorted along z of the coarse grid, as the next stage assumes.
    torch.manual_seed(0)
    enc = PointTransformerEncoder(6, (8, 8), (2, 2), (1, 1), patch_size=16, grid_size=0.01, position_scale=1.0)
    xyz, feat = torch.rand(3, 300, 3) * 0.3, torch.rand(3, 300, 6)
    mask = torch.rand(3, 300) > 0.2
    pts = enc.flatten(xyz, feat, mask).with_feat(torch.rand(int(mask.sum()), 8))
    z_sorted = pts.serialize("z")
    assert z_sorted.order == "z" and z_sorted.serialize("z") is z_sorted
    pool = GridPooling(8, 8)
    with torch.no_grad():
        fast = pool(z_sorted)
        shuffled = z_sorted.permute(torch.randperm(pts.feat.shape[0]), None)  # same points, order unknown
        slow = pool(shuffled)
        transposed = pool(z_sorted.serialize("z-trans"))  # sorted along the other curve: must sort
    for other in (slow, transposed):
        for a, b in ((fast.feat, other.feat), (fast.xyz, other.xyz), (fast.grid, other.grid),
                     (fast.batch, other.batch)):
            torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    key = serial_key(fast.batch, fast.grid, "z")
    assert fast.order == "z" and bool((key[1:] > key[:-1]).all())  # one point per voxel, z-sorted


@pytest.mark.parametrize("stem_poolings", [0, 1])
def test_point_encoder_sample_alone_equals_sample_in_a_batch(stem_poolings: int):
    # B = 1 takes the unpadded fast path (full patches + a shorter last one); a batch pads every
    # sample to whole patches and masks. Both must encode a cloud identically.
    torch.manual_seed(0)
    enc = PointTransformerEncoder(6, (16, 16), (2, 2), (1, 1), patch_size=32, grid_size=0.02, position_scale=1.0,
                                  stem_poolings=stem_poolings).eval()
    xyz, feat = torch.rand(2, 150, 3) * 0.4, torch.rand(2, 150, 6)
    mask = torch.ones(2, 150, dtype=torch.bool)
    mask[1, 97:] = False  # the second cloud is shorter: patches end mid-way
    with torch.no_grad():
        tokens, token_mask = enc(xyz, feat, mask)
        for i in range(2):
            alone, alone_mask = enc(xyz[i : i + 1], feat[i : i + 1], mask[i : i + 1])
            n = int(alone_mask.sum())
            assert int(token_mask[i].sum()) == n
            torch.testing.assert_close(alone[0, :n], tokens[i][token_mask[i]], atol=1e-5, rtol=1e-5)


def test_stem_pooling_attends_over_one_point_per_coarse_voxel():
    # point_stem_poolings=1: the first stage sees one point per occupied voxel of twice the input
    # grid, so a cloud whose points are all repeated (a resampled scan) encodes exactly like the
    # unrepeated one, and the token count is the number of occupied voxels of the last stage.
    torch.manual_seed(0)
    grid = 0.02
    enc = PointTransformerEncoder(6, (16,), (2,), (1,), patch_size=32, grid_size=grid, position_scale=1.0,
                                  stem_poolings=1).eval()
    xyz, feat = torch.rand(1, 200, 3) * 0.3, torch.rand(1, 200, 6)
    mask = torch.ones(1, 200, dtype=torch.bool)
    with torch.no_grad():
        tokens, token_mask = enc(xyz, feat, mask)
        repeated, repeated_mask = enc(xyz.repeat(1, 2, 1), feat.repeat(1, 2, 1), mask.repeat(1, 2))
    voxels = torch.floor((xyz[0] - xyz[0].amin(0)) / grid).long().div(2, rounding_mode="floor").unique(dim=0)
    assert tokens.shape[1] == int(token_mask.sum()) == voxels.shape[0] < 200
    torch.testing.assert_close(repeated, tokens, atol=1e-6, rtol=1e-6)
    assert bool(repeated_mask.all())


def test_stem_pooling_adds_no_parameters():
    # init_weights_from a checkpoint of the authors' layout works for a stem-pooled policy (the default).
    assert RTV3Config(device="cpu").point_stem_poolings == 1
    plain, pooled = make_policy(point_stem_poolings=0).state_dict(), make_policy().state_dict()
    assert {k: v.shape for k, v in plain.items()} == {k: v.shape for k, v in pooled.items()}
    with pytest.raises(ValueError, match="point_stem_poolings"):
        RTV3Config(device="cpu", point_stem_poolings=-1)


# ----------------------------------------------------------------------------- shapes and masks


def test_output_shapes(policy: RTV3Policy, batch: dict):
    b, cfg = 3, policy.config
    chunk = policy.predict_action_chunk(observation_only(batch))
    assert chunk.shape == (b, cfg.horizon, 6) and torch.isfinite(chunk).all()
    modes, log_w = policy.predict_modes(observation_only(batch))
    assert modes.shape == (b, cfg.num_maneuver_classes, cfg.horizon, 6) and log_w.shape == (b, cfg.num_maneuver_classes)
    # The most likely chunk is the mode trajectory of the most likely class.
    best = log_w.argmax(-1)
    torch.testing.assert_close(chunk, modes[torch.arange(b), best], atol=1e-5, rtol=1e-5)
    policy.reset()
    single = observation_only(batch)
    single[ft.STATE] = batch[ft.STATE][:, -1]
    action = policy.select_action(single)
    assert action.shape == (b, 6)
    policy.train()
    loss, info = policy.forward(batch)
    policy.eval()
    assert loss.ndim == 0 and torch.isfinite(loss)
    assert {"loss", "nll", "kl", "beta", "mutual_information", "z_logit_clip"} <= set(info)


def test_padded_actions_do_not_change_the_loss(policy: RTV3Policy, batch: dict):
    padded = dict(batch)
    pad = torch.zeros_like(batch[f"{ft.ACTION}_is_pad"])
    pad[:, 8:] = True
    padded[f"{ft.ACTION}_is_pad"] = pad
    loss_a, _ = policy.forward(padded)
    changed = dict(padded)
    changed[ft.ACTION] = batch[ft.ACTION].clone()
    changed[ft.ACTION][:, 8:] = 7.0  # garbage after the episode end
    loss_b, _ = policy.forward(changed)
    torch.testing.assert_close(loss_a, loss_b)
    changed[ft.ACTION][:, 3] += 0.5  # a real step does count
    loss_c, _ = policy.forward(changed)
    assert not torch.allclose(loss_a, loss_c)


def test_select_action_history_queue_matches_full_history(policy: RTV3Policy, batch: dict):
    obs = observation_only(batch)
    expected = policy.predict_action_chunk(obs)[:, 0]
    policy.reset()
    for t in range(policy.config.n_obs_steps):
        step = dict(obs)
        step[ft.STATE] = batch[ft.STATE][:, t]
        action = policy.select_action(step)
    torch.testing.assert_close(action, expected, atol=1e-5, rtol=1e-5)
    # A first call repeats the observation to fill the history (LeRobot queue semantics).
    policy.reset()
    first = dict(obs)
    first[ft.STATE] = batch[ft.STATE][:, -1]
    repeated = dict(obs)
    repeated[ft.STATE] = batch[ft.STATE][:, -1:].expand(-1, policy.config.n_obs_steps, -1)
    torch.testing.assert_close(policy.select_action(first), policy.predict_action_chunk(repeated)[:, 0])
    # update_history=False answers for the same window without advancing it.
    peek = policy.select_action(first, update_history=False)
    torch.testing.assert_close(peek, policy.select_action(first, update_history=False))
    # Changing the batch size mid-episode is an error.
    with pytest.raises(ValueError, match="reset"):
        policy.select_action({k: v[:1] for k, v in first.items()})
    policy.reset()


def test_packed_environment_state_equals_separate_keys(policy: RTV3Policy, batch: dict):
    obs = observation_only(batch)
    packed = ft.pack_context(obs[ft.POINT_CLOUD], obs[ft.POINT_CLOUD_MASK], obs[ft.GRASPS], obs[ft.GRASPS_MASK])
    only_packed = {ft.STATE: obs[ft.STATE], "observation.environment_state": packed}
    torch.testing.assert_close(policy.predict_action_chunk(obs), policy.predict_action_chunk(only_packed))


# ----------------------------------------------------------------------------- learning


def test_loss_decreases_on_a_fixed_batch():
    policy = make_policy(seed=3, transformer_dropout=0.0, history_noise_translation=0.0, history_noise_rotation=0.0)
    batch = make_scene_batch(policy.config, batch=4, seed=2)
    optimizer = torch.optim.Adam(policy.get_optim_params(), lr=2e-3)
    policy.train()
    losses = []
    for _ in range(30):
        optimizer.zero_grad()
        loss, info = policy.forward(batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
        optimizer.step()
        losses.append(info["nll"])
    assert int(policy.train_step) == 30
    assert losses[-1] < losses[0] - 0.5 * abs(losses[0]), losses
    # The learned most-likely first action points the way the user was going.
    policy.eval()
    predicted = policy.predict_action_chunk(observation_only(batch))[:, 0, :3]
    truth = batch[ft.ACTION][:, 0, :3]
    assert torch.nn.functional.cosine_similarity(predicted, truth, dim=-1).mean() > 0.5


def test_grasp_context_steers_the_prediction():
    """Standing still, the only cue to where the user goes is the grasp set: the model must use it.

    Boxes are spread over the table (sd 0.2 m); the EE history is static. Without the grasp encoder
    the same training reaches a cosine of about 0.6 on held-out scenes, with it about 0.85.
    """
    policy = make_policy(seed=0, transformer_dropout=0.0, use_point_encoder=False, num_points=64, max_grasps=4)
    optimizer = torch.optim.Adam(policy.get_optim_params(), lr=1e-3)

    def standing_still(seed: int) -> dict:
        batch = make_scene_batch(policy.config, batch=32, seed=seed, grasps_valid=1, box_spread=0.2)
        state = batch[ft.STATE][:, :1].expand_as(batch[ft.STATE]).clone()
        state[..., ft.EE_TWIST] = 0.0
        return {**batch, ft.STATE: state}

    policy.train()
    for step in range(80):
        optimizer.zero_grad()
        loss, _ = policy.forward(standing_still(100 + step))
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
        optimizer.step()
    policy.eval()
    held_out = standing_still(999)
    predicted = policy.predict_action_chunk(observation_only(held_out))[:, 0, :3]
    cosine = torch.nn.functional.cosine_similarity(predicted, held_out[ft.ACTION][:, 0, :3], dim=-1).mean()
    assert cosine > 0.75, float(cosine)


# ----------------------------------------------------------------------------- equivariance


@pytest.mark.parametrize("factorized", [True, False])
def test_se3_equivariance(factorized: bool):
    policy = make_policy(seed=4, factorized_rotation=factorized).eval()
    batch = make_scene_batch(policy.config, batch=2, seed=5)
    obs = observation_only(batch)
    g = torch.Generator().manual_seed(6)
    transform = se3.make_transform(se3.so3_exp(2.0 * torch.randn(3, generator=g)), torch.randn(3, generator=g))
    moved = transform_world(obs, transform)
    assert not torch.allclose(moved[ft.STATE], obs[ft.STATE])
    torch.testing.assert_close(policy.predict_action_chunk(moved), policy.predict_action_chunk(obs), atol=1e-4,
                               rtol=1e-4)
    a, b = policy.predict_step0_mixture(obs), policy.predict_step0_mixture(moved)
    torch.testing.assert_close(a.log_weights, b.log_weights, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(a.trans_mean, b.trans_mean, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(a.trans_cov, b.trans_cov, atol=1e-4, rtol=1e-4)


# ----------------------------------------------------------------------------- mixture


@pytest.mark.parametrize("factorized", [True, False])
def test_step0_mixture_is_a_valid_unscaled_mixture(factorized: bool):
    policy = make_policy(seed=7, factorized_rotation=factorized).eval()
    batch = make_scene_batch(policy.config, batch=2, seed=8)
    obs = observation_only(batch)
    mixture = policy.predict_step0_mixture(obs)
    k = policy.config.num_maneuver_classes
    assert isinstance(mixture, TwistMixture) and mixture.num_classes == k
    torch.testing.assert_close(mixture.weights.sum(-1), torch.ones(2))
    assert mixture.trans_mean.shape == (2, k, 3) and mixture.trans_cov.shape == (2, k, 3, 3)
    torch.testing.assert_close(mixture.trans_cov, mixture.trans_cov.transpose(-1, -2))
    assert (torch.linalg.eigvalsh(mixture.trans_cov) > 0).all()
    omega, gamma = mixture.rotation_given_translation(mixture.trans_mean)
    assert omega.shape == (2, k, 3) and gamma.shape == (2, k, 3, 3)
    assert (torch.linalg.eigvalsh(gamma) > 0).all()
    # Consistency with the most likely action, which is in unscaled m/s: the argmax class's means.
    best = mixture.log_weights.argmax(-1)
    action = policy.predict_action_chunk(obs)[:, 0]
    torch.testing.assert_close(action[:, :3], mixture.trans_mean[torch.arange(2), best], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(action[:, 3:], omega[torch.arange(2), best], atol=1e-5, rtol=1e-4)
    # The rotation depends on the translation it is conditioned on.
    omega2, gamma2 = mixture.rotation_given_translation(mixture.trans_mean + 0.1)
    assert not torch.allclose(omega, omega2)
    # Several translations per class in one call (leading dims) = one call each.
    omega_both, gamma_both = mixture.rotation_given_translation(torch.stack([mixture.trans_mean,
                                                                            mixture.trans_mean + 0.1]))
    assert omega_both.shape == (2, 2, k, 3) and gamma_both.shape == (2, 2, k, 3, 3)
    torch.testing.assert_close(omega_both, torch.stack([omega, omega2]), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(gamma_both, torch.stack([gamma, gamma2]), atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="rotation_given_translation"):
        mixture.rotation_given_translation(mixture.trans_mean[:, 0])


def test_translation_scale_is_undone_in_outputs(policy: RTV3Policy, batch: dict):
    """Doubling translation_scale with weights rescaled to match gives the same unscaled outputs."""
    obs = observation_only(batch)
    m1 = policy.predict_step0_mixture(obs)
    # Covariance in m/s units: scaling network outputs by 1/5 means cov scales by 1/25.
    raw = policy.model.decoder
    enc = policy.model.encode(policy._inference_inputs(obs, update_history=False))
    start, prev = policy.model._expand_classes(enc)
    h = raw.step(start, prev, start.state)[0]
    net = raw.translation(h, start.z)
    torch.testing.assert_close(m1.trans_mean.reshape(-1, 3), net.mean / 5.0)
    torch.testing.assert_close(m1.trans_cov.reshape(-1, 3, 3), net.covariance() / 25.0)


# ----------------------------------------------------------------------------- persistence


def test_save_load_round_trip(tmp_path, policy: RTV3Policy, batch: dict):
    obs = observation_only(batch)
    policy.train_step.fill_(123)
    policy.save_pretrained(tmp_path)
    assert (tmp_path / "model.safetensors").is_file() and (tmp_path / "config.json").is_file()
    card = (tmp_path / "README.md").read_text()
    assert "RT-V3" in card and "Maneuver classes K: 10" in card
    loaded = RTV3Policy.from_pretrained(tmp_path)
    assert int(loaded.train_step) == 123
    assert loaded.config.num_points == policy.config.num_points
    torch.testing.assert_close(loaded.predict_action_chunk(obs), policy.predict_action_chunk(obs), atol=0, rtol=0)
    a, b = loaded.predict_step0_mixture(obs), policy.predict_step0_mixture(obs)
    torch.testing.assert_close(a.trans_cov, b.trans_cov, atol=0, rtol=0)
    policy.train_step.zero_()


def test_init_weights_from_starts_fine_tuning(tmp_path, policy: RTV3Policy, batch: dict):
    """``--policy.init_weights_from=DIR`` (fine-tuning with the rtv3 processors) copies the weights and
    the step counter, is consumed (the new checkpoint loads on its own), and names a bad folder."""
    obs = observation_only(batch)
    policy.train_step.fill_(77)
    policy.save_pretrained(tmp_path / "start")
    tuned = make_policy(seed=5, init_weights_from=str(tmp_path / "start")).eval()
    assert int(tuned.train_step) == 77 and tuned.config.init_weights_from is None
    torch.testing.assert_close(tuned.predict_action_chunk(obs), policy.predict_action_chunk(obs), atol=0, rtol=0)
    policy.train_step.zero_()
    tuned.save_pretrained(tmp_path / "tuned")
    assert RTV3Policy.from_pretrained(tmp_path / "tuned").config.init_weights_from is None
    with pytest.raises(FileNotFoundError, match="init_weights_from"):
        make_policy(init_weights_from=str(tmp_path / "missing"))


# ----------------------------------------------------------------------------- bad input


def test_malformed_batches_give_clear_errors(policy: RTV3Policy, batch: dict):
    obs = observation_only(batch)
    bad = dict(obs)
    bad[ft.POINT_CLOUD] = obs[ft.POINT_CLOUD].clone()
    bad[ft.POINT_CLOUD][0, -1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="observation.point_cloud"):
        policy.predict_action_chunk(bad)
    bad = dict(obs)
    bad[ft.STATE] = obs[ft.STATE].clone()
    bad[ft.STATE][1, 2, 0] = float("inf")
    with pytest.raises(ValueError, match="observation.state"):
        policy.predict_action_chunk(bad)
    bad = dict(obs)
    bad[ft.STATE] = obs[ft.STATE][..., :20]
    with pytest.raises(ValueError, match="observation.state"):
        policy.predict_action_chunk(bad)
    bad = dict(obs)
    bad[ft.STATE] = obs[ft.STATE][:, :5]
    with pytest.raises(ValueError, match="T=8"):
        policy.predict_action_chunk(bad)
    bad = dict(obs)
    bad[ft.GRASPS] = obs[ft.GRASPS][..., :8]
    with pytest.raises(ValueError, match="observation.grasps"):
        policy.predict_action_chunk(bad)
    bad = {k: v for k, v in obs.items() if k != ft.GRASPS_MASK}
    with pytest.raises(KeyError, match="observation.grasps_mask"):
        policy.predict_action_chunk(bad)
    with pytest.raises(KeyError, match="scene context"):
        policy.predict_action_chunk({ft.STATE: obs[ft.STATE]})
    bad = dict(obs)
    bad[ft.POINT_CLOUD] = obs[ft.POINT_CLOUD][:2]
    with pytest.raises(ValueError, match="batch size"):
        policy.predict_action_chunk(bad)
    wrong_action = dict(batch)
    wrong_action[ft.ACTION] = batch[ft.ACTION][:, :5]
    with pytest.raises(ValueError, match="'action' has shape"):
        policy.forward(wrong_action)
    nan_action = dict(batch)
    nan_action[ft.ACTION] = batch[ft.ACTION].clone()
    nan_action[ft.ACTION][0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="'action' contains NaN"):
        policy.forward(nan_action)
    single_step = dict(batch)
    single_step[ft.STATE] = batch[ft.STATE][:, -1]
    with pytest.raises(ValueError, match="training needs the history"):
        policy.forward(single_step)


def test_no_valid_grasp_uses_the_null_token(policy: RTV3Policy):
    batch = make_scene_batch(policy.config, batch=2, seed=9, grasps_valid=0)
    obs = observation_only(batch)
    chunk = policy.predict_action_chunk(obs)
    assert torch.isfinite(chunk).all()
    # Garbage in padded grasp rows is ignored.
    noisy = dict(obs)
    noisy[ft.GRASPS] = obs[ft.GRASPS] + torch.randn_like(obs[ft.GRASPS])
    torch.testing.assert_close(policy.predict_action_chunk(noisy), chunk)
    # Same with no valid point at all.
    empty = dict(obs)
    empty[ft.POINT_CLOUD_MASK] = torch.zeros_like(obs[ft.POINT_CLOUD_MASK])
    assert torch.isfinite(policy.predict_action_chunk(empty)).all()
    loss, _ = policy.forward({**batch, ft.POINT_CLOUD_MASK: empty[ft.POINT_CLOUD_MASK]})
    assert torch.isfinite(loss)


def test_grasp_encoding_ignores_padding_slots_and_their_order(policy: RTV3Policy):
    # Inference drops padded grasp slots before the set encoder (a scene fills ~10 of 64); the
    # encoding of a set must not depend on where the padding sits, how much there is, or the
    # order of the valid grasps, in a batch of rows with different counts.
    torch.manual_seed(3)
    encoder = policy.model.grasp_encoder.eval()
    m, f = 12, GRASP_FEATURE_DIM
    feat = torch.randn(3, m, f)
    valid = torch.zeros(3, m, dtype=torch.bool)
    valid[0, [1, 4, 9]] = True
    valid[1, [0, 2, 3, 5, 6, 11]] = True
    valid[2, :2] = True
    query = torch.randn(3, encoder.decoder.query.in_features)
    with torch.no_grad():
        packed = encoder(feat, valid, query)
        for i in range(3):
            own = feat[i][valid[i]]
            shuffled = own[torch.randperm(own.shape[0])]
            padded = torch.cat([shuffled, torch.randn(5, f)])[None]  # garbage padding at the end
            alone = encoder(padded, torch.arange(padded.shape[1])[None] < own.shape[0], query[i : i + 1])
            torch.testing.assert_close(alone[0], packed[i], atol=1e-5, rtol=1e-5)


def test_grasp_subset_augmentation_keeps_the_target():
    from rtv3_maniskill.policies.rtv3.batch import SceneContext, subsample_grasps

    mask = torch.zeros(50, 40, dtype=torch.bool)
    mask[:, :30] = True
    target = torch.randint(0, 30, (50,))
    ctx = SceneContext(torch.zeros(50, 4, 6), torch.ones(50, 4, dtype=torch.bool), torch.zeros(50, 40, 9), mask)
    kept = subsample_grasps(ctx, target, min_keep=10).grasp_mask
    assert kept[torch.arange(50), target].all()
    assert (kept <= mask).all()
    counts = kept.sum(1)
    assert counts.min() >= 10 and counts.max() <= 30 and counts.float().std() > 0
    # log-uniform sizes: small sets (the target nearly explicit) far more often than uniform sizes
    # would give (3 of 30 sizes are <= 3: 10 %)
    many = SceneContext(torch.zeros(4000, 4, 6), torch.ones(4000, 4, dtype=torch.bool), torch.zeros(4000, 40, 9),
                        mask[:1].expand(4000, -1))
    goal = torch.zeros(4000, dtype=torch.long)
    log_counts = subsample_grasps(many, goal).grasp_mask.sum(1).float()
    assert log_counts.min() >= 1 and log_counts.max() <= 30
    assert (log_counts <= 3).float().mean() > 0.25


def test_twist_noise_and_sampled_rotation_conditioning_act_in_training_only():
    """Both regularisers change the training loss (so they are on) and leave inference untouched."""
    base = make_policy(seed=12, transformer_dropout=0.0, history_noise_translation=0.0, history_noise_rotation=0.0)
    batch = make_scene_batch(base.config, batch=3, seed=13)
    variants = {
        "twist_noise": dict(twist_noise_linear=0.05, twist_noise_angular=0.2),
        "sampled": dict(rotation_conditioning="sampled"),
        "rotation_resample": dict(history_rotation_resample_prob=1.0),
    }
    base.train()
    torch.manual_seed(0)
    reference = float(base.forward(batch)[0].detach())
    base.eval()
    ref_chunk = base.predict_action_chunk(observation_only(batch))
    for name, overrides in variants.items():
        policy = make_policy(seed=12, transformer_dropout=0.0, history_noise_translation=0.0,
                             history_noise_rotation=0.0, **overrides)
        policy.load_state_dict(base.state_dict())
        policy.train()
        torch.manual_seed(0)
        loss = policy.forward(batch)[0].detach()
        assert torch.isfinite(loss) and abs(float(loss) - reference) > 1e-4, name
        policy.eval()
        policy.reset()
        assert torch.allclose(policy.predict_action_chunk(observation_only(batch)), ref_chunk, atol=1e-6), name


def test_resampled_past_rotation_is_a_consistent_turn_into_the_current_pose():
    """The augmented history is a physically consistent motion: it ends at the current pose, turns at
    one constant rate, its body twists integrate to its poses, positions are kept, and unselected
    samples are untouched."""
    from rtv3_maniskill.policies.rtv3.egocentric import resample_past_rotation

    torch.manual_seed(4)
    batch, steps, dt = 3, 8, ft.DT
    start = se3.se3_exp(torch.randn(batch, 6, dtype=torch.float64))
    twists = torch.randn(batch, steps, 6, dtype=torch.float64) * 0.2
    poses = se3.integrate_body_twists(start, twists[:, :-1], dt)  # (B, T-1): poses after each of the first twists
    poses = torch.cat([start[:, None], poses], 1)  # (B, T)
    selected = torch.tensor([True, False, True])
    new_poses, new_twists = resample_past_rotation(poses, twists, selected, 1.0, dt)
    assert torch.equal(new_poses[1], poses[1]) and torch.equal(new_twists[1], twists[1])
    assert torch.allclose(new_poses[:, -1], poses[:, -1])
    assert torch.allclose(new_poses[..., :3, 3], poses[..., :3, 3])
    for b in (0, 2):
        rate = new_twists[b, :, 3:]
        assert torch.allclose(rate, rate[:1].expand_as(rate)) and rate.abs().max() <= 1.0
        assert not torch.allclose(new_poses[b, 0, :3, :3], poses[b, 0, :3, :3], atol=1e-3)
        # stepping the new body twists from each new pose reaches the next one (rotation exactly,
        # translation to first order in dt, as the world-frame velocity is kept)
        stepped = se3.integrate_body_twists(new_poses[b, :-1], new_twists[b, :-1, None], dt)[:, 0]
        assert torch.allclose(stepped[:, :3, :3], new_poses[b, 1:, :3, :3], atol=1e-9)
        original = se3.integrate_body_twists(poses[b, :-1], twists[b, :-1, None], dt)[:, 0]
        assert torch.allclose(stepped[:, :3, 3] - new_poses[b, :-1, :3, 3],
                              original[:, :3, 3] - poses[b, :-1, :3, 3], atol=2e-3)


# ----------------------------------------------------------------------------- ablations


@pytest.mark.parametrize(
    "overrides",
    [
        dict(use_grasp_encoder=False),
        dict(use_point_encoder=False),
        dict(point_stem_poolings=0),
        dict(use_grasp_encoder=False, use_point_encoder=False),
        dict(factorized_rotation=False),
        dict(num_maneuver_classes=25),
        dict(factorized_rotation=False, rotation_conditioning="sampled"),
        dict(rotation_conditioning="sampled", twist_noise_linear=0.05, twist_noise_angular=0.2,
             history_rotation_resample_prob=0.5),
    ],
)
def test_ablation_configs_run(overrides: dict):
    policy = make_policy(seed=10, **overrides)
    batch = make_scene_batch(policy.config, batch=2, seed=11)
    policy.train()
    loss, _ = policy.forward(batch)
    loss.backward()
    grads = [p.grad for p in policy.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    policy.eval()
    assert policy.predict_action_chunk(observation_only(batch)).shape == (2, 12, 6)
    assert policy.predict_step0_mixture(observation_only(batch)).num_classes == policy.config.num_maneuver_classes
    has = {n.split(".")[1] for n, _ in policy.named_parameters() if n.startswith("model.")}
    assert ("grasp_encoder" in has) == policy.config.use_grasp_encoder
    assert ("point_encoder" in has) == policy.config.use_point_encoder


@pytest.mark.parametrize("factorized", [True, False])
def test_free_running_step_gives_the_mode_of_the_same_state(factorized: bool):
    """The free-running decoder feeds back the state's most likely action from the heads it already
    evaluated for the log-likelihood: the same action as ``mode_action``, outside the autograd graph."""
    policy = make_policy(seed=12, factorized_rotation=factorized)
    decoder, k = policy.model.decoder, policy.config.num_maneuver_classes
    gen = torch.Generator().manual_seed(13)
    h = torch.randn(5, decoder.gru.hidden_size, generator=gen, requires_grad=True)
    z = torch.nn.functional.one_hot(torch.arange(5) % k, k).float()
    actions = torch.randn(5, 6, generator=gen)
    ll, mode = decoder._state_log_likelihood(h, z, actions, 50.0, "demonstrated")
    assert torch.equal(mode, decoder.mode_action(h, z))
    assert not mode.requires_grad and ll.requires_grad


# ----------------------------------------------------------------------------- LeRobot integration


def _write_dataset(root, cfg: RTV3Config, episodes: int = 2, frames: int = 24):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    n, m = cfg.num_points, cfg.max_grasps
    features = {
        ft.STATE: {"dtype": "float32", "shape": (ft.STATE_DIM,), "names": None},
        ft.POINT_CLOUD: {"dtype": "float32", "shape": (n, 6), "names": None},
        ft.POINT_CLOUD_MASK: {"dtype": "float32", "shape": (n,), "names": None},
        ft.GRASPS: {"dtype": "float32", "shape": (m, ft.GRASP_DIM), "names": None},
        ft.GRASPS_MASK: {"dtype": "float32", "shape": (m,), "names": None},
        ft.ACTION: {"dtype": "float32", "shape": (6,), "names": None},
        ft.TARGET_GRASP: {"dtype": "int64", "shape": (1,), "names": None},
    }
    dataset = LeRobotDataset.create("local/rtv3_test", fps=ft.FPS, features=features, root=root, use_videos=False)
    long_cfg = RTV3Config(device="cpu", num_points=n, max_grasps=m, n_obs_steps=1, horizon=frames)
    for episode in range(episodes):
        ep = make_scene_batch(long_cfg, batch=1, seed=20 + episode)
        # One trajectory of `frames` poses: integrate the episode's actions from its start state.
        start = se3.pose_to_matrix(ep[ft.STATE][0, 0, 0:3], ep[ft.STATE][0, 0, 3:7])
        poses = torch.cat([start[None], se3.integrate_body_twists(start, ep[ft.ACTION][0], ft.DT)[:-1]])
        for t in range(frames):
            state = ep[ft.STATE][0, 0].clone()
            state[0:7] = se3.matrix_to_pose(poses[t])
            state[ft.EE_TWIST] = ep[ft.ACTION][0, max(t - 1, 0)]
            dataset.add_frame(
                {
                    ft.STATE: state,
                    ft.POINT_CLOUD: ep[ft.POINT_CLOUD][0, 0],
                    ft.POINT_CLOUD_MASK: ep[ft.POINT_CLOUD_MASK][0, 0],
                    ft.GRASPS: ep[ft.GRASPS][0, 0],
                    ft.GRASPS_MASK: ep[ft.GRASPS_MASK][0, 0],
                    ft.ACTION: ep[ft.ACTION][0, t],
                    ft.TARGET_GRASP: torch.zeros(1, dtype=torch.int64),
                    "task": "grasp",
                }
            )
        dataset.save_episode()
    dataset.finalize()
    return dataset


def test_lerobot_dataset_factory_and_processors_train(tmp_path):
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    from lerobot.policies.factory import make_policy as lerobot_make_policy
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()  # what lerobot-train / lerobot-eval do first
    assert get_policy_class("rtv3") is RTV3Policy

    # One row per sample: the policy cuts the history and the future actions from the training cache
    # (tests/policies/test_training_cache.py), this dataset having no observation.state_history
    cfg = RTV3Config(device="cpu", num_points=64, max_grasps=8)
    written = _write_dataset(tmp_path / "ds", cfg)
    meta = written.meta
    assert meta.total_episodes == 2 and meta.fps == ft.FPS
    dataset = LeRobotDataset("local/rtv3_test", root=tmp_path / "ds",
                             delta_timestamps=resolve_delta_timestamps(cfg, meta))
    sample = dataset[0]
    assert sample[ft.STATE].shape == (ft.STATE_DIM,) and sample[ft.ACTION].shape == (6,)

    policy = lerobot_make_policy(cfg, ds_meta=meta)
    assert isinstance(policy, RTV3Policy)
    assert set(cfg.input_features) >= {ft.STATE, ft.POINT_CLOUD, ft.GRASPS_MASK}
    preprocessor, postprocessor = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    loader = torch.utils.data.DataLoader(dataset, batch_size=4, shuffle=True,
                                         generator=torch.Generator().manual_seed(0))
    optimizer = cfg.get_optimizer_preset().build(policy.get_optim_params())
    policy.train()
    for _, raw in zip(range(3), loader):
        batch = preprocessor(raw)
        # the privileged target index reaches the policy (grasp-subset augmentation)
        assert torch.equal(batch[ft.TARGET_GRASP], raw[ft.TARGET_GRASP])
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        assert torch.isfinite(loss)
    # Inference through the same processors with a single unbatched observation.
    policy.eval()
    policy.reset()
    frame = dataset.hf_dataset[5]
    obs = {k: torch.as_tensor(frame[k]) for k in cfg.input_features}
    action = postprocessor(policy.select_action(preprocessor(obs)))
    assert action.shape == (1, 6) and torch.isfinite(action).all()

    # The model card names the training dataset, also after a reload and a second save.
    from huggingface_hub import ModelCard

    policy.save_pretrained(tmp_path / "saved")
    assert ModelCard.load(tmp_path / "saved" / "README.md").data.datasets == "local/rtv3_test"
    RTV3Policy.from_pretrained(tmp_path / "saved").save_pretrained(tmp_path / "resaved")
    assert ModelCard.load(tmp_path / "resaved" / "README.md").data.datasets == "local/rtv3_test"


@pytest.mark.sim
def test_lerobot_train_cli_trains_and_checkpoints(tmp_path):
    """``lerobot-train --policy.type=rtv3`` end to end, then reload the checkpoint with its processors."""
    import importlib.metadata
    import os
    import subprocess
    import sys

    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    cfg = RTV3Config(device="cpu", num_points=64, max_grasps=8)
    _write_dataset(tmp_path / "ds", cfg, frames=16)  # no observation.state_history: the training cache gives it
    args = [
        sys.executable, "-m", "lerobot.scripts.lerobot_train",
        "--dataset.repo_id=local/rtv3_test", f"--dataset.root={tmp_path / 'ds'}",
        "--policy.type=rtv3", "--policy.device=cpu",  # N = 64, M = 8 are read from the dataset features
        "--policy.push_to_hub=false", "--steps=2", "--batch_size=2", "--num_workers=0", "--save_freq=2",
        f"--output_dir={tmp_path / 'out'}", "--wandb.enable=false",
    ]
    try:
        importlib.metadata.distribution("lerobot_policy_rtv3")
    except importlib.metadata.PackageNotFoundError:  # plugin shim not installed: name the package instead
        args.append("--policy.discover_packages_path=rtv3_maniskill.policies.rtv3")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run(args, capture_output=True, text=True, timeout=240, cwd=tmp_path, env=env)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    checkpoint = tmp_path / "out" / "checkpoints" / "last" / "pretrained_model"
    assert (checkpoint / "README.md").is_file()
    from huggingface_hub import ModelCard

    assert ModelCard.load(checkpoint / "README.md").data.datasets == "local/rtv3_test"  # not "local"
    policy = RTV3Policy.from_pretrained(checkpoint)
    assert int(policy.train_step) == 2 and policy.config.num_points == 64
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    frame = LeRobotDataset("local/rtv3_test", root=tmp_path / "ds").hf_dataset[3]
    obs = {k: torch.as_tensor(frame[k]) for k in policy.config.input_features}
    action = postprocessor(policy.select_action(preprocessor(obs)))
    assert action.shape == (1, 6) and torch.isfinite(action).all()


@pytest.mark.sim
def test_eval_env_shows_the_policy_the_target_whose_pregrasp_counts():
    """``lerobot-eval``'s view scores reaching the episode's target: by default the policy sees only
    that candidate (the planning protocol); ``--env.context=all`` shows every candidate."""
    from rtv3_maniskill.lerobot_env import GraspClutterLeRobotEnv, RTV3ClutterEnvConfig

    masks = {}
    for context in ("target", "all"):
        env = GraspClutterLeRobotEnv(render_mode=None, context=context, num_points=64, max_grasps=8)
        try:
            obs, _ = env.reset(seed=3, options={"target_grasp_index": 1})
            target = int(env._env.unwrapped.target_grasp_index[0])
        finally:
            env.close()
        unpacked = ft.unpack_context(torch.from_numpy(obs["environment_state"]), 64, 8)
        masks[context] = unpacked[ft.GRASPS_MASK]
    assert target == 1
    assert masks["target"].tolist() == [0.0, 1.0] + [0.0] * 6
    assert masks["all"].sum() > 1 and masks["all"][1] == 1.0
    with pytest.raises(ValueError, match="nearest"):
        RTV3ClutterEnvConfig(context="nearest")


@pytest.mark.sim
def test_env_context_size_mismatch_names_the_sizes_and_the_eval_flags():
    """``lerobot-eval --env.type=rtv3_clutter`` with another point count / grasp count than the
    policy's: the error names the feature, both sizes and ``--env.num_points`` / ``--env.max_grasps``."""
    from lerobot.envs.factory import make_env
    from lerobot.envs.utils import preprocess_observation

    from rtv3_maniskill.lerobot_env import RTV3ClutterEnvConfig

    envs = make_env(RTV3ClutterEnvConfig(num_points=64, max_grasps=8, episode_length=3), n_envs=1)
    vec_env = next(iter(next(iter(envs.values())).values()))
    try:
        observation, _ = vec_env.reset(seed=0)
    finally:
        vec_env.close()
    batch = preprocess_observation(observation)  # what lerobot-eval hands the policy's preprocessor
    assert set(batch) == {ft.STATE, "observation.environment_state"}

    policy = make_policy(num_points=32, max_grasps=8).eval()
    with pytest.raises(ValueError) as points:
        policy.select_action(batch)
    message = str(points.value)
    assert "observation.environment_state" in message and "observation.point_cloud" in message
    assert "64 points (--env.num_points)" in message and "num_points=32" in message
    assert "--env.num_points=32" in message and "--env.max_grasps=8" in message

    policy = make_policy(num_points=64, max_grasps=16).eval()
    with pytest.raises(ValueError) as grasps:
        policy.select_action(batch)
    message = str(grasps.value)
    assert "8 candidates (--env.max_grasps)" in message and "max_grasps=16" in message
    assert "--env.max_grasps=16" in message

    # the sizes that match run
    policy = make_policy(num_points=64, max_grasps=8).eval()
    assert policy.select_action(batch).shape == (1, 6)
