"""``rtv3 scene``: render a random clutter scene with its point cloud and grasp candidates."""

from __future__ import annotations

import argparse
from pathlib import Path

from rtv3_maniskill.cli.scene_args import add_scene_arguments, resolve_scene_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0, help="scene seed (same seed, same scene)")
    add_scene_arguments(parser, default_preset="paper", execution=False)
    parser.add_argument("--num-objects", type=int, default=None,
                        help="objects (default: Poisson(4)+1; 4 requested for packed_ycb)")
    parser.add_argument("--output", type=Path, default=Path("outputs/scene.png"), help="PNG to write")


def run(args: argparse.Namespace) -> int:
    import gymnasium as gym
    import numpy as np

    import rtv3_maniskill  # noqa: F401  (registers GraspClutter-v1)
    from rtv3_maniskill.visualization import save_scene_figure

    resolve_scene_arguments(args)
    if not args.output.parent.exists():
        args.output.parent.mkdir(parents=True)
    env = gym.make(
        "GraspClutter-v1",
        obs_mode="pointcloud",
        render_mode="rgb_array",
        scene_type=args.scene_type,
        num_objects=args.num_objects,
        object_source=args.objects,
    )
    obs, info = env.reset(seed=args.seed)
    image = env.render()[0].cpu().numpy()
    extra = obs["extra"]
    points = extra["point_cloud"][0][extra["point_cloud_mask"][0] > 0].cpu().numpy()
    grasps = extra["grasps"][0][extra["grasps_mask"][0] > 0].cpu().numpy()
    target = int(info["target_grasp_index"][0])
    base = env.unwrapped
    names = ", ".join(o.name for o in base.layouts[0].objects)
    save_scene_figure(
        args.output, image, points, grasps, target, f"GraspClutter-v1 seed {args.seed} ({args.scene_type}): {names}"
    )
    env.close()
    objects = len(base.layouts[0].objects)
    print(f"scene seed {args.seed}: {objects} objects ({names}), {len(grasps)} grasp candidates on "
          f"{len(np.unique(base.grasp_sets[0].object_ids))} objects, {len(points)} points; image -> {args.output}")
    return 0
