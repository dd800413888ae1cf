"""How ``select_action`` latency depends on the point cloud's spatial spread and the point-encoder layout.

Usage: ``python scripts/benchmark_policy_clouds.py [--rounds 5] [--steps 100] [--scene-seed 900000]``

One untrained default-size policy (N = 2048, M = 64) per layout, ``point_stem_poolings`` 1 (default)
and 0 (the authors'), sharing the same weights. Every round times ``--steps`` calls of each
(layout, cloud) pair in turn, so the VM's minute-to-minute drift hits all pairs alike; the table gives
the median over rounds of each round's median, and the tokens the first PTv3 stage attends over.
Clouds: the synthetic layouts of ``benchmark_policy.py --cloud`` and, with ``--scene-seed``, a
rendered ``GraspClutter-v1`` scene.
"""

from __future__ import annotations

import argparse
import statistics

import torch
from benchmark_policy import (
    SYNTHETIC_CLOUDS,
    first_stage_tokens,
    rendered_scene_observation,
    synthetic_observation,
    time_select_action,
)
from tqdm import tqdm

from rtv3_maniskill import features
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds over every (layout, cloud) pair")
    parser.add_argument("--steps", type=int, default=100, help="select_action calls timed per pair and round")
    parser.add_argument("--scene-seed", type=int, default=None, help="also time this rendered GraspClutter-v1 scene")
    args = parser.parse_args()
    if args.rounds < 1 or args.steps < 1:
        parser.error("--rounds and --steps must be >= 1")
    torch.set_num_threads(1)
    torch.manual_seed(0)

    policies = {stem: RTV3Policy(RTV3Config(device="cpu", point_stem_poolings=stem)).eval() for stem in (1, 0)}
    policies[0].load_state_dict(policies[1].state_dict())
    observations: dict[str, dict[str, torch.Tensor]] = {}
    for cloud in SYNTHETIC_CLOUDS:
        observations[cloud] = synthetic_observation(policies[1].config, cloud)
    if args.scene_seed is not None:
        observations[f"scene {args.scene_seed}"] = rendered_scene_observation(args.scene_seed, policies[1].config)

    pairs = [(stem, cloud) for stem in policies for cloud in observations]
    tokens = {(stem, cloud): first_stage_tokens(policies[stem], observations[cloud]) for stem, cloud in pairs}
    medians: dict[tuple[int, str], list[float]] = {pair: [] for pair in pairs}
    for _ in tqdm(range(args.rounds), desc="rounds"):
        for stem, cloud in pairs:
            policy, obs = policies[stem], observations[cloud]
            policy.reset()
            for _ in range(10):
                policy.select_action(obs)
            wall, _ = time_select_action(policy, obs, args.steps)
            medians[(stem, cloud)].append(statistics.median(wall))

    print("| cloud | real points | stem pooling (default): tokens, ms | authors' layout: tokens, ms |")
    print("| --- | --- | --- | --- |")
    for cloud, obs in observations.items():
        real = int(obs[features.POINT_CLOUD_MASK].sum())
        cells = [f"{tokens[(stem, cloud)]}, {statistics.median(medians[(stem, cloud)]):.2f}" for stem in (1, 0)]
        print(f"| {cloud} | {real} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
