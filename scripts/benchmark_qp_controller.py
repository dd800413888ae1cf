"""Time one NEO QP step (control/neo_qp.py) with the clutter scene's obstacle pairs.

For a few GraspClutter-v1 scenes, configurations are taken on the joint-space line from the ready
pose to an IK solution at the target's pre-grasp (the hand among the objects, where most pairs lie
within the influence distance). Each configuration is timed for the whole step (distances + QP) and
for its parts. Prints medians in ms. Single-threaded (Pinocchio, coal and DAQP use one core).

    .venv/bin/python scripts/benchmark_qp_controller.py --scenes 4 --configs 40
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import qpsolvers  # noqa: E402
import torch  # noqa: E402

import rtv3_maniskill  # noqa: E402, F401  (registers the task)
from rtv3_maniskill.control.neo_qp import NeoConfig, NeoSafetyFilter  # noqa: E402
from rtv3_maniskill.datasets.panda_model import PandaKinematics  # noqa: E402
from rtv3_maniskill.tasks.scene_geometry import READY_QPOS  # noqa: E402
from rtv3_maniskill.tasks.twist_controller import target_object_index  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--configs", type=int, default=40, help="configurations per scene")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per configuration")
    parser.add_argument("--solver", default="daqp", choices=qpsolvers.available_solvers)
    args = parser.parse_args()
    torch.set_num_threads(1)
    kin = PandaKinematics()
    env = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_ee_twist_qp", num_points=256)
    step_ms, dist_ms, rows, pairs = [], [], [], []
    twist = np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.2])
    for seed in range(args.scenes):
        env.reset(seed=seed)
        base = env.unwrapped
        filt = NeoSafetyFilter(base.layouts[0], NeoConfig(solver=args.solver), target_object=target_object_index(env),
                               kinematics=kin)
        goal, ok = kin.ik_from_seed(base.target_pregrasp_pose[0].double().numpy(), READY_QPOS, max_iters=500)
        if not ok:
            continue
        ctrl = filt.controller
        for s in np.linspace(0.0, 1.0, args.configs):
            q = (1 - s) * READY_QPOS + s * goal
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                step = filt.filter(q, twist)
                t1 = time.perf_counter()
                ctrl.world.nearest_points(q, ctrl.damped_pairs, ctrl.config.influence_distance)
                t2 = time.perf_counter()
                step_ms.append(1e3 * (t1 - t0))
                dist_ms.append(1e3 * (t2 - t1))
            rows.append(step.num_collision_constraints)
        pairs.append(len(ctrl.damped_pairs))
    env.close()
    if not step_ms:
        raise SystemExit("no scene had an IK solution at its pre-grasp; try more --scenes")
    print(f"solver {args.solver}; {len(pairs)} scenes, {len(rows)} configurations, {args.repeats} calls each")
    print(f"obstacle pairs per scene (damped): median {int(np.median(pairs))}, max {max(pairs)}")
    reach = ctrl.config.influence_distance
    print(f"collision constraints within {reach} m: median {int(np.median(rows))}, max {max(rows)}")
    p90 = np.percentile(step_ms, 90)
    print(f"QP step (distances + Jacobians + QP): median {np.median(step_ms):.2f} ms, p90 {p90:.2f} ms")
    print(f"  of which distance queries (coal):   median {np.median(dist_ms):.2f} ms")


if __name__ == "__main__":
    main()
