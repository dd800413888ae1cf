"""``rtv3 visualize-episode``: picture of one dataset episode (scene, grasps, target, trajectory, twists)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", type=Path, required=True, help="dataset folder written by `rtv3 generate`")
    parser.add_argument("--episode", type=int, default=0, help="episode index")
    parser.add_argument("--output", type=Path, default=Path("outputs/episode.png"), help="PNG to write")


def run(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill import features as F
    from rtv3_maniskill.features import REPO_ID
    from rtv3_maniskill.visualization import grasp_array_to_poses, plot_point_cloud_and_grasps

    if not (args.dataset / "meta" / "info.json").exists():
        raise SystemExit(f"error: {args.dataset} holds no LeRobot dataset (meta/info.json missing)")
    dataset = LeRobotDataset(REPO_ID, root=args.dataset, episodes=[args.episode])
    if len(dataset) == 0:
        raise SystemExit(f"error: episode {args.episode} not found in {args.dataset}")
    frames = [dataset[i] for i in range(len(dataset))]
    state = np.stack([f[F.STATE].numpy() for f in frames])
    action = np.stack([f[F.ACTION].numpy() for f in frames])
    first = frames[0]
    # stored flat (F.STORED_FLAT): back to (N, 6) / (M, 9)
    cloud = F.unflatten(F.POINT_CLOUD, first[F.POINT_CLOUD].numpy())[first[F.POINT_CLOUD_MASK].numpy() > 0]
    grasps = F.unflatten(F.GRASPS, first[F.GRASPS].numpy())[first[F.GRASPS_MASK].numpy() > 0]
    target = int(first[F.TARGET_GRASP].reshape(-1)[0])

    fig = plt.figure(figsize=(13, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    plot_point_cloud_and_grasps(ax, cloud, grasp_array_to_poses(grasps), grasps[:, 7], target,
                                trajectory=state[:, F.EE_POS])
    ax.set_title(f"episode {args.episode}: {first['task']}")
    ax2 = fig.add_subplot(2, 2, 2)
    t = np.arange(len(action)) / F.FPS
    for i, name in enumerate("xyz"):
        ax2.plot(t, action[:, i], label=f"v{name}")
    ax2.set_ylabel("m/s")
    ax2.legend(ncol=3, fontsize=8)
    ax2.set_title("action: TCP body twist")
    ax3 = fig.add_subplot(2, 2, 4)
    for i, name in enumerate("xyz"):
        ax3.plot(t, action[:, 3 + i], label=f"w{name}")
    ax3.set_ylabel("rad/s")
    ax3.set_xlabel("time [s]")
    ax3.legend(ncol=3, fontsize=8)
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=110)
    print(f"episode {args.episode}: {len(frames)} frames, '{first['task']}' -> {args.output}")
    return 0
