"""Does the prior read its turn from the goal, or continue the turn it sees in its history?

Records fresh planner demonstrations (the expert of ``rtv3 generate``, authors' start poses) and
feeds each one to the prior frame by frame, its history the expert's own (teacher forcing), the
context the target grasp only (as in ``rtv3 evaluate planning``). Per frame it compares the
prior's most likely next twist with the expert's: the cosine of the translational and of the
rotational velocity, and the ratio of angular speeds. The first frame of a demonstration has a
still history, so there the turn must come from the goal; on later frames the expert's past turn
is visible. A prior that scores well on later frames only is continuing its past, and in closed
loop its past is its own.

Usage: ``python scripts/teacher_forced_rotation.py [--policy.path DIR ...] [--scenes 4] [--seed 9]``
(several ``--policy.path`` are compared on the same demonstrations).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))


def main() -> None:
    import gymnasium as gym
    from tqdm import tqdm

    import rtv3_maniskill  # noqa: F401  (registers the task)
    from rtv3_maniskill import features
    from rtv3_maniskill.datasets.demonstrations import DemonstrationRecorder
    from rtv3_maniskill.datasets.planner import PandaPlanner
    from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT, load_policy
    from rtv3_maniskill.records import SCENE_SEED_STRIDE

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy.path", dest="policy_paths", type=Path, action="append",
                        help="checkpoint folder (repeatable; default: the shipped one)")
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--seed", type=int, default=9, help="scene i has seed SEED*100000 + 10 + i")
    parser.add_argument("--targets-per-scene", type=int, default=4)
    args = parser.parse_args()
    if args.scenes < 1 or args.targets_per_scene < 1:
        parser.error("--scenes and --targets-per-scene must be >= 1")
    torch.set_num_threads(1)
    paths = args.policy_paths or [SHIPPED_CHECKPOINT]
    policies = [load_policy(p) for p in paths]
    sizes = {(int(p.config.num_points), int(p.config.max_grasps)) for p in policies}
    if len(sizes) != 1:
        raise SystemExit(f"error: the checkpoints differ in num_points / max_grasps: {sorted(sizes)}")
    num_points, max_grasps = sizes.pop()
    env = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_joint_pos_vel",
                   reconfiguration_freq=0, num_points=num_points, max_grasps=max_grasps)
    recorder = DemonstrationRecorder(env, PandaPlanner, end_at="pregrasp")
    rows: list[list[dict[str, float]]] = [[] for _ in policies]
    demos = 0
    for scene in tqdm(range(args.scenes), desc="scenes"):
        valid = recorder.load_scene(args.seed * SCENE_SEED_STRIDE + 10 + scene)
        cloud, cloud_mask = recorder.base.capture_point_cloud()
        for grasp in range(0, min(valid, 2 * args.targets_per_scene), 2):
            episode = recorder.record(grasp, seed=100 + grasp)
            if isinstance(episode, str):
                continue
            demos += 1
            mask = torch.zeros(1, max_grasps)
            mask[0, episode.target_grasp_index] = 1.0
            for policy, out in zip(policies, rows):
                policy.reset()
                for k in range(episode.pregrasp_step):
                    observation = {
                        features.STATE: torch.from_numpy(episode.state[k : k + 1]).float(),
                        features.POINT_CLOUD: cloud.float(), features.POINT_CLOUD_MASK: cloud_mask.float(),
                        features.GRASPS: torch.from_numpy(episode.grasps[None]).float(), features.GRASPS_MASK: mask,
                    }
                    action = policy.select_action(observation)[0].numpy()
                    expert = episode.action[k]
                    out.append(dict(first=float(k == 0), v=_cosine(action[:3], expert[:3]),
                                    w=_cosine(action[3:], expert[3:]),
                                    speed=float(np.linalg.norm(action[3:]) / max(np.linalg.norm(expert[3:]), 1e-6))))
    env.close()
    print(f"{demos} demonstrations; medians over frames (first = the still-history first frame of each)")
    print("| checkpoint | frames | cos v | cos w | |w| / expert |w| | first frames: cos w | first: |w| ratio |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for path, out in zip(paths, rows):
        if not out:
            continue
        later = [r for r in out if not r["first"]]
        first = [r for r in out if r["first"]]

        def med(items, key):
            return float(np.median([r[key] for r in items])) if items else float("nan")

        print(f"| {path} | {len(out)} | {med(later, 'v'):.3f} | {med(later, 'w'):.3f} | {med(later, 'speed'):.2f} "
              f"| {med(first, 'w'):.2f} | {med(first, 'speed'):.2f} |")


if __name__ == "__main__":
    main()
