"""Benchmark the RT-V3 policy on CPU: ``select_action`` latency and training throughput.

Usage: ``python benchmarks/benchmark_policy.py [--threads 2] [--steps 200] [--repeats 3] [--train-batches 5]
[--policy.path DIR] [--cloud table-box|surface|volume] [--scene-seed S] [--point-stem-poolings K] [--device cuda]``

Inputs are synthetic but shaped like the dataset (N = 2048 points, M = 64 grasps, T = 8, H = 12), every
point and grasp slot real. With stem pooling the cost also depends on how many 15 mm voxels the cloud
occupies (the first stage attends over one token per voxel), so ``--cloud`` picks its spatial spread:
``table-box`` (default: 1,024 points on a 60 x 60 cm table, 1,024 in a 6 cm box; ~830 tokens),
``surface`` (2,048 points on a 7.5 mm grid, the densest a voxel-filtered depth scan of a plane gets;
~520 tokens) or ``volume`` (uniform in 60 x 60 x 30 cm, almost one token per point: no depth camera
gives such a cloud, the stem pooling's worst case). ``--scene-seed S`` times a rendered
``GraspClutter-v1`` scene instead (depth-camera cloud with N slots, of which a scan fills a few hundred
after the 7.5 mm voxel filter; the scene's own grasps).
``select_action`` is timed ``--repeats`` times ``--steps`` calls; the result is the median of the
repeats' medians (a shared VM drifts by 20-50 % from minute to minute), each repeat is printed.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from rtv3_maniskill import features
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

SYNTHETIC_CLOUDS = ("table-box", "surface", "volume")


def synthetic_xyz(batch: int, n: int, cloud: str, g: torch.Generator) -> torch.Tensor:
    """``(batch, n, 3)`` world-frame points (m) of the ``cloud`` layout (see the module docstring)."""
    if cloud == "table-box":
        table = (torch.rand(batch, n // 2, 3, generator=g) * torch.tensor([0.6, 0.6, 0.0])
                 + torch.tensor([0.0, -0.3, 0.0]))
        box = torch.rand(batch, n - n // 2, 3, generator=g) * 0.06 + torch.tensor([0.4, 0.0, 0.0])
        return torch.cat([table, box], 1)
    if cloud == "surface":  # row-major 7.5 mm grid, each point jittered inside its voxel
        side = math.ceil(math.sqrt(n))
        index = torch.arange(n)
        cells = torch.stack([index // side, index % side], -1).float()
        xy = (cells + torch.rand(batch, n, 2, generator=g)) * 0.0075 + torch.tensor([0.2, -0.2])
        return torch.cat([xy, torch.zeros(batch, n, 1)], -1)
    if cloud == "volume":
        return torch.rand(batch, n, 3, generator=g) * torch.tensor([0.6, 0.6, 0.3]) + torch.tensor([0.0, -0.3, 0.0])
    raise ValueError(f"unknown synthetic cloud {cloud!r}; use one of {SYNTHETIC_CLOUDS}")


def synthetic_batch(batch: int, cfg: RTV3Config, seed: int = 0, cloud: str = "table-box") -> dict[str, torch.Tensor]:
    """A batch with a straight-line EE history, points laid out as ``cloud``, grasps around the box."""
    g = torch.Generator().manual_seed(seed)
    t, h, n, m = cfg.n_obs_steps, cfg.horizon, cfg.num_points, cfg.max_grasps
    state = torch.zeros(batch, t, features.STATE_DIM)
    start = torch.tensor([0.3, 0.0, 0.4]) + 0.05 * torch.randn(batch, 1, 3, generator=g)
    velocity = torch.tensor([0.0, 0.05, -0.1])
    state[..., features.EE_POS] = start + velocity * features.DT * torch.arange(t)[None, :, None]
    state[..., 3] = 0.0
    state[..., 4] = 1.0  # gripper pointing down (180 deg about x)
    state[..., 7:10] = velocity * torch.tensor([1.0, -1.0, -1.0])
    xyz = synthetic_xyz(batch, n, cloud, g)
    point_cloud = torch.cat([xyz, torch.rand(batch, n, 3, generator=g)], -1)
    grasp_pos = torch.tensor([0.43, 0.03, 0.1]) + 0.02 * torch.randn(batch, m, 3, generator=g)
    grasp_quat = torch.tensor([0.0, 1.0, 0.0, 0.0]).expand(batch, m, 4)
    grasps = torch.cat([grasp_pos, grasp_quat, torch.full((batch, m, 1), 0.05), torch.ones(batch, m, 1)], -1)
    return {
        features.STATE: state,
        features.POINT_CLOUD: point_cloud,
        features.POINT_CLOUD_MASK: torch.ones(batch, n),
        features.GRASPS: grasps,
        features.GRASPS_MASK: torch.ones(batch, m),
        features.ACTION: ((velocity * torch.tensor([1.0, -1.0, -1.0])).repeat(batch, h, 2)
                          * torch.tensor([1.0] * 3 + [0.0] * 3)),
        f"{features.ACTION}_is_pad": torch.zeros(batch, h, dtype=torch.bool),
        # training applies the grasp-subset augmentation
        features.TARGET_GRASP: torch.zeros(batch, 1, dtype=torch.long),
    }


def synthetic_observation(cfg: RTV3Config, cloud: str = "table-box") -> dict[str, torch.Tensor]:
    """Single-step policy inputs ``(1, ...)`` of :func:`synthetic_batch`: the current state ``(1, 27)`` and
    the scene context."""
    full = synthetic_batch(1, cfg, cloud=cloud)
    single = {k: v for k, v in full.items() if k.startswith("observation.")}
    single[features.STATE] = full[features.STATE][:, -1]  # one control step: (1, 27)
    return single


def time_select_action(policy: RTV3Policy, single: dict[str, torch.Tensor], steps: int,
                       sync=lambda: None) -> tuple[list[float], list[float]]:
    """Wall and process-CPU times (ms) of ``steps`` consecutive ``select_action`` calls; ``sync`` waits
    for the device after each."""
    wall, cpu = [], []
    for _ in range(steps):
        t0, c0 = time.perf_counter(), time.process_time()
        policy.select_action(single)
        sync()
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return wall, cpu


def machine_check() -> str:
    """How fast this machine is right now: float32 512 x 512 matmul throughput and the cost of one small
    tensor op (one thread each). A shared VM drifts; quote this line with a latency so runs can be compared."""
    a, x = torch.randn(512, 512), torch.randn(16)
    for _ in range(10):
        a @ a
    t0 = time.perf_counter()
    for _ in range(50):
        a @ a
    gflops = 2 * 512**3 * 50 / (time.perf_counter() - t0) / 1e9
    t0 = time.perf_counter()
    for _ in range(5000):
        x + 1
    small_op_us = (time.perf_counter() - t0) / 5000 * 1e6
    return f"machine check: 512x512 float32 matmul {gflops:.0f} GFLOPS, one small tensor op {small_op_us:.2f} us"


def rendered_scene_observation(scene_seed: int, cfg: RTV3Config) -> dict[str, torch.Tensor]:
    """Single-step policy inputs ``(1, ...)`` of scene ``scene_seed`` of ``GraspClutter-v1`` (rendered cloud)."""
    import gymnasium as gym

    import rtv3_maniskill  # noqa: F401  (registers GraspClutter-v1)

    env = gym.make("GraspClutter-v1", obs_mode="pointcloud", control_mode="pd_ee_twist",
                   num_points=cfg.num_points, max_grasps=cfg.max_grasps)
    try:
        obs, _ = env.reset(seed=scene_seed)
        return features.observation_from_env(obs)
    finally:
        env.close()


def first_stage_tokens(policy: RTV3Policy, single: dict[str, torch.Tensor]) -> int:
    """Points entering the first PTv3 stage for the observation ``single`` (one extra, untimed call)."""
    seen = []
    first_block = policy.model.point_encoder.backbone.stages[0][0]
    hook = first_block.register_forward_pre_hook(lambda module, args: seen.append(args[0].feat.shape[0]))
    try:
        policy.select_action(single, update_history=False)
    finally:
        hook.remove()
    return seen[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--threads", type=int, default=1,
                        help="intra-op threads (1 is robust on a shared 2-core machine)")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the policy (e.g. cuda); inputs start on the CPU, as an observation does, "
                             "and every timed call waits for the device")
    parser.add_argument("--steps", type=int, default=200, help="select_action calls timed per repeat")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats of --steps calls")
    parser.add_argument("--train-batches", type=int, default=5)
    parser.add_argument("--train-batch-size", type=int, default=64)
    parser.add_argument("--point-patch-size", type=int, default=None, help="override the PTv3 patch size (120)")
    parser.add_argument("--point-stem-poolings", type=int, default=None,
                        help="override RTV3Config.point_stem_poolings of the untrained default-size policy")
    parser.add_argument("--cloud", choices=SYNTHETIC_CLOUDS, default="table-box",
                        help="spatial layout of the synthetic cloud "
                             "(see the module docstring; ignored with --scene-seed)")
    parser.add_argument("--scene-seed", type=int, default=None,
                        help="time a rendered GraspClutter-v1 scene (its cloud and grasps) instead of synthetic inputs")
    parser.add_argument("--policy.path", dest="policy_path", default=None,
                        help="time a checkpoint with its own N and M (e.g. the shipped one, N = 512) instead of "
                             "an untrained default-size policy (N = 2048, M = 64)")
    args = parser.parse_args()
    if args.steps < 1 or args.repeats < 1 or args.threads < 1 or args.train_batches < 1:
        parser.error("--steps, --repeats, --threads and --train-batches must be >= 1")
    try:
        device = torch.device(args.device)
    except RuntimeError as err:
        parser.error(f"--device {args.device!r}: {err}")
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch finds no CUDA device on this machine")
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    print(machine_check())

    if args.policy_path is not None:
        policy = RTV3Policy.from_pretrained(args.policy_path)
        cfg = policy.config
    else:
        overrides = {} if args.point_patch_size is None else {"point_patch_size": args.point_patch_size}
        if args.point_stem_poolings is not None:
            overrides["point_stem_poolings"] = args.point_stem_poolings
        cfg = RTV3Config(device="cpu", **overrides)
        policy = RTV3Policy(cfg)
    policy.to(device)
    print(f"parameters: {sum(p.numel() for p in policy.parameters()):,}  device: {device}  threads: "
          f"{torch.get_num_threads()}  N={cfg.num_points} M={cfg.max_grasps}  "
          f"point_stem_poolings={cfg.point_stem_poolings}")

    if args.scene_seed is None:
        single = synthetic_observation(cfg, args.cloud)
        inputs = f"synthetic {args.cloud}"
    else:
        single = rendered_scene_observation(args.scene_seed, cfg)
        inputs = f"scene {args.scene_seed}"
    print(f"inputs: {inputs}, {int(single[features.POINT_CLOUD_MASK].sum())} of {cfg.num_points} point slots real, "
          f"{int(single[features.GRASPS_MASK].sum())} of {cfg.max_grasps} grasp slots")
    policy.eval()
    policy.reset()
    if policy.model.point_encoder is not None:
        print(f"first point stage attends over {first_stage_tokens(policy, single)} tokens")
    for _ in range(10):
        policy.select_action(single)
    sync()
    times, cpu_times, repeat_medians = [], [], []
    for _ in range(args.repeats):
        this_repeat, this_cpu = time_select_action(policy, single, args.steps, sync)
        times += this_repeat
        cpu_times += this_cpu
        repeat_medians.append(statistics.median(this_repeat))
    q = statistics.quantiles(times, n=20)
    median = statistics.median(repeat_medians)
    print("select_action per-repeat medians (ms): " + ", ".join(f"{m:.2f}" for m in repeat_medians))
    print(
        f"select_action (B=1, N={cfg.num_points}, M={cfg.max_grasps}): median {median:.2f} ms "
        f"(median of {args.repeats} repeat medians), p5 {q[0]:.2f} ms, p95 {q[-1]:.2f} ms over "
        f"{len(times)} calls (process CPU time median {statistics.median(cpu_times):.2f} ms; target <= 8 ms wall)"
    )
    t0 = time.perf_counter()
    for _ in range(20):
        policy.predict_step0_mixture(single, update_history=False)
    sync()
    print(f"predict_step0_mixture (B=1): mean {(time.perf_counter() - t0) / 20 * 1e3:.2f} ms")

    batch = {k: v.to(device) for k, v in synthetic_batch(args.train_batch_size, cfg, seed=1).items()}
    policy.train()
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    loss, _ = policy.forward(batch)
    loss.backward()
    optimizer.step()
    sync()
    t0 = time.perf_counter()
    for _ in range(args.train_batches):
        optimizer.zero_grad()
        loss, _ = policy.forward(batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
        optimizer.step()
    sync()
    elapsed = time.perf_counter() - t0
    rate = args.train_batches * args.train_batch_size / elapsed
    print(
        f"training (batch {args.train_batch_size}, forward+backward+step): {rate:.1f} samples/s, "
        f"{elapsed / args.train_batches * 1e3:.0f} ms/step"
    )


if __name__ == "__main__":
    main()
