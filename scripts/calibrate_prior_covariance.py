"""How overconfident is the prior where its own closed loop takes it? A covariance scale from data.

The shared controller multiplies the prior's step-0 covariances by ``prior_covariance_scale``
before the gate and the fusion (Kalman gain ``K = s Sigma_z (s Sigma_z + S_u)^-1``). A prior that
is calibrated needs ``s = 1``. This script measures the ``s`` that the data ask for: on the
relabelled states of a DAgger dataset (``rtv3 dagger``: states that the prior, or a user through
Direct or RT-V3, visited in closed loop; the target is the planner's next step from there) and, for
reference, on windows of planner demonstrations (``rtv3 generate``, the prior's training
distribution). Per dataset it prints, for each scale on a grid, the mixture's mean negative
log-likelihood of the expert's next translation velocity (nats) and the share of windows whose
expert velocity lies inside the chi2(0.85, 3) region of the nearest class (the OOD gate with a
perfect user), and the maximum-likelihood scale.

    python scripts/calibrate_prior_covariance.py --dataset data/dagger_r3 --dataset data/heldout

Translation only (the rotation Gaussians are conditioned on it and scaled the same way).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

SCALES = (0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)


def load_windows(root: Path, relabelled_only: bool, max_windows: int, seed: int) -> tuple[dict, torch.Tensor]:
    """A policy batch of ``max_windows`` frames of the dataset at ``root`` (first frames of its
    episodes when ``relabelled_only``) and the expert's next translation velocity ``(B, 3)``
    (m/s, EE body frame), from the frame's pose to the next frame's."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill import features, se3
    from rtv3_maniskill.datasets.lerobot_export import REPO_ID

    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"no LeRobot dataset at {root} (missing meta/info.json)")
    hf = LeRobotDataset(REPO_ID, root=root).hf_dataset
    if features.STATE_HISTORY not in hf.column_names:
        raise ValueError(f"dataset at {root} has no '{features.STATE_HISTORY}' column (not an rtv3 dataset?)")
    table = hf.select_columns(["episode_index", "frame_index", features.STATE]).with_format("numpy")[:]
    episode = np.asarray(table["episode_index"]).reshape(-1)
    frame = np.asarray(table["frame_index"]).reshape(-1)
    states = np.asarray(table[features.STATE], dtype=np.float64)
    has_next = np.zeros(len(frame), dtype=bool)
    has_next[:-1] = (episode[1:] == episode[:-1]) & (frame[1:] == frame[:-1] + 1)
    usable = has_next & ((frame == 0) if relabelled_only else (frame >= features.HISTORY_STEPS - 1))
    rows = np.flatnonzero(usable)
    if len(rows) == 0:
        raise ValueError(f"dataset at {root} has no usable window")
    rng = np.random.default_rng(seed)
    rows = np.sort(rng.choice(rows, size=min(max_windows, len(rows)), replace=False))
    keys = [features.STATE_HISTORY, features.POINT_CLOUD, features.POINT_CLOUD_MASK, features.GRASPS,
            features.GRASPS_MASK]
    picked = hf.select_columns(keys).with_format("numpy")[rows]
    batch = {k: torch.as_tensor(np.stack(picked[k]), dtype=torch.float32) for k in keys}
    now, nxt = (torch.as_tensor(states[r]) for r in (rows, rows + 1))
    poses = [se3.pose_to_matrix(s[:, features.EE_POS], s[:, features.EE_QUAT]) for s in (now, nxt)]
    return batch, se3.body_twist(poses[0], poses[1], features.DT)[:, :3]


def scale_table(log_n: torch.Tensor, maha_sq: torch.Tensor, log_weights: torch.Tensor,
                scales: tuple[float, ...], alpha: float = 0.85) -> list[dict[str, float]]:
    """Per scale ``s``: mean mixture NLL of the targets and coverage of the nearest class when every
    class covariance is ``s`` times the prior's. ``log_n`` (class log-densities), ``maha_sq`` and
    ``log_weights``: ``(B, K)`` under the unscaled covariances (3-D translation Gaussians); scaling a
    covariance by ``s`` divides the Mahalanobis distance by ``s`` and adds ``3/2 log s`` to the NLL."""
    from scipy.stats import chi2

    threshold = chi2.ppf(alpha, 3)
    out = []
    for s in scales:
        log_n_s = log_n + 0.5 * maha_sq * (1.0 - 1.0 / s) - 1.5 * math.log(s)
        nll = -torch.logsumexp(log_weights + log_n_s, -1)
        covered = (maha_sq.min(-1).values / s) <= threshold
        out.append(dict(scale=s, nll=float(nll.mean()), covered=float(covered.double().mean())))
    return out


def main() -> None:
    from tqdm import tqdm

    from rtv3_maniskill.policies.rtv3.checkpoints import SHIPPED_CHECKPOINT, load_policy
    from rtv3_maniskill.shared_control import posterior

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy.path", dest="policy_path", type=Path, default=SHIPPED_CHECKPOINT)
    parser.add_argument("--dataset", type=Path, action="append", required=True,
                        help="LeRobot dataset folder (repeatable); a DAgger dataset is read at its relabelled "
                             "states, any other at every full window")
    parser.add_argument("--max-windows", type=int, default=1500, help="windows drawn per dataset (seeded)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batch-size", type=int, default=64)
    args = parser.parse_args()
    if args.max_windows < 1 or args.batch_size < 1:
        parser.error("--max-windows and --batch-size must be >= 1")
    torch.set_num_threads(1)
    policy = load_policy(args.policy_path)
    for root in args.dataset:
        generation = root / "rtv3_generation.json"
        relabelled = generation.is_file() and json.loads(generation.read_text()).get("source") == "dagger"
        batch, target = load_windows(root, relabelled, args.max_windows, args.seed)
        parts: dict[str, list[torch.Tensor]] = {"logn": [], "maha": [], "logw": []}
        n = target.shape[0]
        for start in tqdm(range(0, n, args.batch_size), desc=root.name, unit="batch"):
            chunk = {k: v[start : start + args.batch_size] for k, v in batch.items()}
            with torch.inference_mode():
                mixture = policy.predict_step0_mixture(chunk, update_history=False)
            mu, cov = mixture.trans_mean.double(), mixture.trans_cov.double()
            log_n, maha = posterior.gaussian_log_prob_and_mahalanobis_sq(
                target[start : start + args.batch_size, None], mu, cov)
            parts["logn"].append(log_n)
            parts["maha"].append(maha)
            parts["logw"].append(mixture.log_weights.double())
        rows = scale_table(*(torch.cat(parts[k]) for k in ("logn", "maha", "logw")), SCALES)
        best = min(rows, key=lambda r: r["nll"])
        kind = "relabelled closed-loop states" if relabelled else "demonstration windows"
        print(f"\n{root} ({n} {kind}); maximum-likelihood scale on the grid: {best['scale']:g}")
        print("| scale | mean NLL (nats) | nearest class covers (chi2 0.85) |")
        print("|---:|---:|---:|")
        for r in rows:
            print(f"| {r['scale']:g} | {r['nll']:.2f} | {100 * r['covered']:.1f} % |")


if __name__ == "__main__":
    main()
