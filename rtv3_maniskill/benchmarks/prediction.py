"""Trajectory-prediction benchmark of the RT-V3 prior (paper Table I, left half; docs/PAPER_DETAILS.md "Metrics").

Test windows: ``T + H`` consecutive frames of one episode (20 = 8 + 12), the current step
is the T-th frame (index 7 counting from 0, "index 8" in the paper's 1-based wording): the
policy reads the T states up to and including it plus the episode's static scene context;
the ground truth is the recorded TCP poses of the H following frames. Only full windows are
used (no padding at either end of an episode).

Prediction: for every maneuver class ``z`` the policy's most likely twist sequence
(:meth:`RTV3Policy.predict_modes`) integrated from the current pose,
``T_{k+1} = T_k Exp(a_k dt)`` (paper Sec. IV-D).

Error per step: the paper's pose distance with ``E = T_gt^-1 T_pred``,
``||t_E||_1 + (0.3/pi) ||euler_xyz(E)||_1`` (m, rad), reported x1000. ADE = mean over the H
steps, FDE = last step. Best-of-Mode: the minimum over classes (ADE and FDE minimised
separately, as Trajectron++ does); Most-Likely: the class with the largest ``p(z|h0)``.

The metrics are :mod:`~rtv3_maniskill.benchmarks.prediction_metrics`, the held-out windows
:mod:`~rtv3_maniskill.benchmarks.held_out_windows`; this module evaluates a checkpoint on them.

Held-out episodes are chosen by scene seed (the dataset's ``scene_seed`` column): a range
``A:B`` (A <= seed < B), the last fraction of the dataset's scenes, or all of them (for a
dataset generated with a seed not used for training).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from rtv3_maniskill import features, se3
from rtv3_maniskill.benchmarks.held_out_windows import EpisodeData, load_episodes, make_windows, window_batch
from rtv3_maniskill.benchmarks.prediction_metrics import (
    BASELINES,
    CALIBRATION_ALPHA,
    METRIC_NAMES,
    ade_fde,
    baseline_twists,
    displacement_errors,
    future_poses,
    mode_metrics,
    step0_calibration,
)
from rtv3_maniskill.policies.rtv3.checkpoints import load_policy

PAPER_TABLE1_FULL = {"ade_bom": 26.70, "fde_bom": 37.90, "ade_ml": 32.05, "fde_ml": 47.87}
"""Full RT-V3 in the paper's Table I (their data set), for orientation only."""


def evaluate_windows(
    policy: Any,
    episodes: Sequence[EpisodeData],
    windows: Sequence[tuple[int, int]],
    batch_size: int = 64,
    progress: bool = False,
) -> dict[str, Any]:
    """Mean ADE/FDE (BoM, ML) over ``windows`` and the mean ML error per horizon step.

    ``policy``: an ``RTV3Policy`` (``predict_modes`` and ``config.n_obs_steps`` / ``config.horizon``).
    """
    if not windows:
        raise ValueError("no test windows to evaluate")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    history, horizon = int(policy.config.n_obs_steps), int(policy.config.horizon)
    sums = {name: 0.0 for name in METRIC_NAMES}
    baseline_sums = {f"{b}_{m}": 0.0 for b in BASELINES for m in ("ade", "fde")}
    per_step = torch.zeros(horizon, dtype=torch.float64)
    calibration: dict[str, list[torch.Tensor]] = {}
    for start in tqdm(range(0, len(windows), batch_size), desc="prediction windows", unit="batch",
                      disable=not progress):
        chunk = windows[start : start + batch_size]
        batch, current, gt = window_batch(episodes, chunk, history, horizon)
        twists, log_prior = policy.predict_modes(batch, update_history=False)  # (B, K, H, 6), (B, K)
        metrics = mode_metrics(gt, future_poses(current, twists.double().cpu()), log_prior.double().cpu())
        for name in METRIC_NAMES:
            sums[name] += float(metrics[name].sum())
        per_step += metrics["errors_ml"].sum(0)
        if hasattr(policy, "predict_step0_mixture"):
            mixture = policy.predict_step0_mixture(batch, update_history=False)
            true_v = se3.body_twist(current, gt[:, 0], features.DT)[:, :3]
            for key, value in step0_calibration(mixture, true_v).items():
                calibration.setdefault(key, []).append(value.double().cpu())
        for name, twists in baseline_twists(batch[features.STATE][:, -1].double(), horizon).items():
            ade, fde = ade_fde(displacement_errors(gt, future_poses(current, twists)))
            baseline_sums[f"{name}_ade"] += float(ade.sum())
            baseline_sums[f"{name}_fde"] += float(fde.sum())
    n = len(windows)
    out: dict[str, Any] = {name: sums[name] / n for name in METRIC_NAMES}
    out["per_step_ml"] = (per_step / n).tolist()
    out["baselines"] = {key: value / n for key, value in baseline_sums.items()}
    if calibration:
        cal = {key: torch.cat(values) for key, values in calibration.items()}
        out["step0_calibration"] = dict(
            alpha=CALIBRATION_ALPHA,
            covered_ml=float(cal["covered_ml"].mean()),
            covered_any=float(cal["covered_any"].mean()),
            median_maha_sq_ml=float(cal["maha_sq_ml"].median()),
            mean_nll=float(cal["nll"].mean()),
            median_sigma_ml=float(cal["sigma_ml"].median()),
        )
    return out


def run_prediction_evaluation(
    policy_path: str | Path,
    dataset_root: str | Path,
    seed_range: tuple[int, int] | None = None,
    last_fraction: float | None = None,
    all_scenes: bool = False,
    max_windows: int | None = None,
    batch_size: int = 64,
    seed: int = 0,
    output: str | Path | None = None,
    progress: bool = True,
    policy: Any = None,
) -> dict[str, Any]:
    """Evaluate a checkpoint on the held-out windows of a dataset; returns (and writes to ``output``) the JSON report.

    ``max_windows``: a seeded random subset (``seed``) of the windows when there are more.
    ``policy`` overrides loading ``policy_path``.
    """
    if max_windows is not None and max_windows < 1:
        raise ValueError(f"max_windows must be >= 1, got {max_windows}")
    if policy is None:
        policy = load_policy(policy_path)
    cfg = policy.config
    episodes, held_out = load_episodes(dataset_root, seed_range, last_fraction, all_scenes)
    if episodes:
        n, m = episodes[0].point_cloud.shape[0], episodes[0].grasps.shape[0]
        if (n, m) != (int(cfg.num_points), int(cfg.max_grasps)):
            raise ValueError(
                f"the dataset has N={n} points and M={m} grasps per frame but the policy expects "
                f"N={cfg.num_points}, M={cfg.max_grasps}"
            )
    history, horizon = int(cfg.n_obs_steps), int(cfg.horizon)
    windows = make_windows(episodes, history, horizon)
    if not windows:
        raise ValueError(
            f"no {history + horizon}-step window in the {len(episodes)} held-out episodes ({held_out['rule']})"
        )
    available = len(windows)
    if max_windows is not None and available > max_windows:
        pick = np.random.default_rng(seed).choice(available, size=max_windows, replace=False)
        windows = [windows[i] for i in sorted(pick.tolist())]
    used_episodes = sorted({i for i, _ in windows})
    metrics = evaluate_windows(policy, episodes, windows, batch_size=batch_size, progress=progress)
    report: dict[str, Any] = dict(
        metrics={name: metrics[name] for name in METRIC_NAMES},
        per_step_ml=metrics["per_step_ml"],
        baselines=metrics["baselines"],
        step0_calibration=metrics.get("step0_calibration"),
        units="pose distance x1000: L1 translation (m) + (0.3/pi) * L1 xyz-Euler of T_gt^-1 T_pred (rad)",
        num_windows=len(windows),
        num_windows_available=available,
        num_episodes=len(used_episodes),
        num_scenes=len({episodes[i].scene_seed for i in used_episodes}),
        scene_seeds=sorted({episodes[i].scene_seed for i in used_episodes}),
        held_out=held_out["rule"],
        window=dict(history=history, horizon=horizon, length=history + horizon, current_index=history - 1),
        num_maneuver_classes=int(cfg.num_maneuver_classes),
        policy_path=str(policy_path) if policy_path is not None else None,
        dataset_root=str(dataset_root),
        seed=seed,
        paper_table1_full_rtv3=PAPER_TABLE1_FULL,
    )
    if output is not None:
        path = Path(output).expanduser()
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report, indent=2))
    return report


def format_table(report: dict[str, Any]) -> str:
    """Plain-text table of the four numbers plus what was evaluated."""
    m = report["metrics"]
    lines = [
        f"{'x1000':<19}{'ADE':>8}{'FDE':>8}",
        f"{'Best-of-Mode':<19}{m['ade_bom']:>8.2f}{m['fde_bom']:>8.2f}",
        f"{'Most-Likely':<19}{m['ade_ml']:>8.2f}{m['fde_ml']:>8.2f}",
    ]
    for name in BASELINES:
        b = report.get("baselines", {})
        if f"{name}_ade" in b:
            lines.append(f"{name.replace('_', ' '):<19}{b[name + '_ade']:>8.2f}{b[name + '_fde']:>8.2f}  (reference)")
    cal = report.get("step0_calibration")
    if cal:
        lines.append(
            f"step-0 translation coverage at chi2 {cal['alpha']}: ML class {100 * cal['covered_ml']:.1f} %, "
            f"nearest class {100 * cal['covered_any']:.1f} % (calibrated ~{100 * cal['alpha']:.0f} %); "
            f"median ML sigma {1000 * cal['median_sigma_ml']:.1f} mm/s"
        )
    lines += [
        f"{report['num_windows']} windows of {report['window']['length']} steps "
        f"(of {report['num_windows_available']}), {report['num_episodes']} episodes, "
        f"{report['num_scenes']} scenes ({report['held_out']})",
    ]
    return "\n".join(lines)
