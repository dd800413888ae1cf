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

Held-out episodes are chosen by scene seed (the dataset's ``scene_seed`` column): a range
``A:B`` (A <= seed < B), the last fraction of the dataset's scenes, or all of them (for a
dataset generated with a seed not used for training).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rtv3_maniskill import features, se3

METRIC_SCALE = 1000.0
"""The paper reports pose distances x1000."""
METRIC_NAMES = ("ade_bom", "fde_bom", "ade_ml", "fde_ml")
PAPER_TABLE1_FULL = {"ade_bom": 26.70, "fde_bom": 37.90, "ade_ml": 32.05, "fde_ml": 47.87}
"""Full RT-V3 in the paper's Table I (their data set), for orientation only."""


# ----------------------------------------------------------------------------- metrics


def displacement_errors(
    gt_poses: torch.Tensor, pred_poses: torch.Tensor, rot_weight: float = se3.PLANNING_ROT_WEIGHT
) -> torch.Tensor:
    """Per-step errors ``(..., H)`` x1000 between poses ``(..., H, 4, 4)`` (world frame).

    ``1000 * (||t_E||_1 + rot_weight * ||euler_xyz(E)||_1)`` with ``E = T_gt^-1 T_pred``
    (paper appendix "Distance Metric"). ``pred_poses`` may carry extra leading dims that
    broadcast against ``gt_poses`` (e.g. ``(B, K, H, 4, 4)`` vs ``(B, 1, H, 4, 4)``).
    """
    for name, value in (("gt_poses", gt_poses), ("pred_poses", pred_poses)):
        if value.ndim < 3 or tuple(value.shape[-2:]) != (4, 4):
            raise ValueError(f"{name} must be (..., H, 4, 4) homogeneous transforms, got {tuple(value.shape)}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name} contains NaN or inf")
    return METRIC_SCALE * se3.pose_distance(gt_poses, pred_poses, rot_weight)


def ade_fde(errors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``errors (..., H)`` -> (ADE = mean over the horizon, FDE = last step), each ``(...)``."""
    if errors.ndim < 1 or errors.shape[-1] == 0:
        raise ValueError(f"errors must be (..., H) with H >= 1, got {tuple(errors.shape)}")
    return errors.mean(-1), errors[..., -1]


def future_poses(current: torch.Tensor, twists: torch.Tensor, dt: float = features.DT) -> torch.Tensor:
    """Poses ``(B, [K,] H, 4, 4)`` reached from ``current (B, 4, 4)`` by body twists ``(B, [K,] H, 6)``."""
    if current.ndim != 3 or tuple(current.shape[1:]) != (4, 4):
        raise ValueError(f"current must be (B, 4, 4), got {tuple(current.shape)}")
    if twists.shape[-1] != 6 or twists.ndim not in (3, 4) or twists.shape[0] != current.shape[0]:
        raise ValueError(f"twists must be (B, [K,] H, 6) with B = {current.shape[0]}, got {tuple(twists.shape)}")
    start = current if twists.ndim == 3 else current[:, None].expand(-1, twists.shape[1], 4, 4)
    return se3.integrate_body_twists(start, twists.to(current.dtype), dt)


def mode_metrics(gt_poses: torch.Tensor, mode_poses: torch.Tensor, log_prior: torch.Tensor) -> dict[str, torch.Tensor]:
    """Best-of-Mode and Most-Likely ADE/FDE per window (x1000).

    Args:
        gt_poses: ``(B, H, 4, 4)`` recorded future poses.
        mode_poses: ``(B, K, H, 4, 4)`` most likely future of each maneuver class.
        log_prior: ``(B, K)`` log p(z|h0).

    Returns ``ade_bom, fde_bom, ade_ml, fde_ml`` ``(B,)`` and ``errors_ml`` ``(B, H)``.
    """
    if mode_poses.ndim != 5 or mode_poses.shape[0] != gt_poses.shape[0] or mode_poses.shape[2:] != gt_poses.shape[1:]:
        raise ValueError(
            f"mode_poses must be (B, K, H, 4, 4) matching gt_poses {tuple(gt_poses.shape)}, "
            f"got {tuple(mode_poses.shape)}"
        )
    if tuple(log_prior.shape) != tuple(mode_poses.shape[:2]):
        raise ValueError(f"log_prior must be (B, K) = {tuple(mode_poses.shape[:2])}, got {tuple(log_prior.shape)}")
    errors = displacement_errors(gt_poses[:, None], mode_poses)  # (B, K, H)
    ade, fde = ade_fde(errors)
    best = log_prior.argmax(-1)
    rows = torch.arange(errors.shape[0], device=errors.device)
    return dict(
        ade_bom=ade.min(-1).values,
        fde_bom=fde.min(-1).values,
        ade_ml=ade[rows, best],
        fde_ml=fde[rows, best],
        errors_ml=errors[rows, best],
    )


BASELINES = ("stand_still", "constant_velocity")


def baseline_twists(current_state: torch.Tensor, horizon: int) -> dict[str, torch.Tensor]:
    """Reference predictors from the current state ``(B, 27)``: twists ``(B, H, 6)``.

    ``stand_still``: zero twist; ``constant_velocity``: the body twist realised over the last
    step, repeated. A trained prior should beat both.
    """
    last = current_state[:, features.EE_TWIST]
    return dict(
        stand_still=torch.zeros(last.shape[0], horizon, 6, dtype=last.dtype),
        constant_velocity=last[:, None].expand(-1, horizon, 6),
    )


# ----------------------------------------------------------------------------- episodes and windows


@dataclass
class EpisodeData:
    """One dataset episode: ``states (S, 27)`` and its static context (see ``features.py``)."""

    episode_index: int
    scene_seed: int
    states: np.ndarray
    point_cloud: np.ndarray
    point_cloud_mask: np.ndarray
    grasps: np.ndarray
    grasps_mask: np.ndarray


def parse_seed_range(text: str) -> tuple[int, int]:
    """``"A:B"`` -> ``(A, B)``: the scene seeds ``A <= s < B``."""
    parts = str(text).split(":")
    try:
        low, high = (int(p) for p in parts)
    except ValueError:
        raise ValueError(f"scene-seed range must look like A:B with integers (A <= seed < B), got {text!r}") from None
    if high <= low:
        raise ValueError(f"scene-seed range {text!r} is empty: need A < B (A <= seed < B)")
    return low, high


def select_scene_seeds(
    available: Sequence[int],
    seed_range: tuple[int, int] | None = None,
    last_fraction: float | None = None,
    all_scenes: bool = False,
) -> list[int]:
    """The held-out scene seeds among ``available`` (exactly one rule must be given).

    ``seed_range``: ``A <= s < B``; ``last_fraction``: the largest ``ceil(f * n)`` of the n
    distinct seeds (``rtv3 generate`` numbers scenes in order, so these are the last scenes
    made); ``all_scenes``: every seed.
    """
    rules = sum([seed_range is not None, last_fraction is not None, bool(all_scenes)])
    if rules != 1:
        raise ValueError("choose the held-out episodes with exactly one of: "
                         "scene-seed range, last fraction, all scenes")
    seeds = sorted({int(s) for s in available})
    if seed_range is not None:
        low, high = seed_range
        chosen = [s for s in seeds if low <= s < high]
        if not chosen:
            raise ValueError(
                f"no episode has a scene seed in [{low}, {high}); the dataset's seeds span {seeds[0]}..{seeds[-1]}"
                if seeds else "the dataset has no episodes"
            )
        return chosen
    if last_fraction is not None:
        if not (0.0 < last_fraction <= 1.0) or not math.isfinite(last_fraction):
            raise ValueError(f"last fraction must be in (0, 1], got {last_fraction}")
        if not seeds:
            raise ValueError("the dataset has no episodes")
        return seeds[len(seeds) - max(1, math.ceil(last_fraction * len(seeds))):]
    return seeds


def load_episodes(
    dataset_root: str | Path,
    seed_range: tuple[int, int] | None = None,
    last_fraction: float | None = None,
    all_scenes: bool = False,
) -> tuple[list[EpisodeData], dict[str, Any]]:
    """Held-out episodes of the LeRobot dataset at ``dataset_root`` and a description of the choice."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from rtv3_maniskill.features import REPO_ID

    root = Path(dataset_root).expanduser()
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"no LeRobot dataset at {root} (missing meta/info.json); make one with `rtv3 generate`")
    dataset = LeRobotDataset(REPO_ID, root=root)
    hf = dataset.hf_dataset
    needed = [features.STATE, "episode_index", "index", "scene_seed", features.POINT_CLOUD, features.GRASPS]
    missing = [k for k in needed if k not in hf.column_names]
    if missing:
        raise ValueError(f"dataset at {root} lacks the columns {missing} (not an `rtv3 generate` dataset?)")
    table = hf.select_columns([features.STATE, "episode_index", "scene_seed", "index"]).with_format("numpy")[:]
    episode_of = np.asarray(table["episode_index"]).reshape(-1)
    scene_of = np.asarray(table["scene_seed"]).reshape(-1)
    states = np.asarray(table[features.STATE], dtype=np.float64)
    chosen = set(select_scene_seeds(scene_of.tolist(), seed_range, last_fraction, all_scenes))
    context_keys = [features.POINT_CLOUD, features.POINT_CLOUD_MASK, features.GRASPS, features.GRASPS_MASK]
    context_columns = hf.select_columns(context_keys).with_format("numpy")
    episodes = []
    order = np.lexsort((np.asarray(table["index"]).reshape(-1), episode_of))  # grouped by episode, in frame order
    ids, starts = np.unique(episode_of[order], return_index=True)
    for ep, rows in zip(ids, np.split(order, starts[1:])):
        scene = int(scene_of[rows[0]])
        if scene not in chosen:
            continue
        context = context_columns[int(rows[0])]
        episodes.append(
            EpisodeData(
                episode_index=int(ep),
                scene_seed=scene,
                states=states[rows],
                point_cloud=features.unflatten(features.POINT_CLOUD,
                                               np.asarray(context[features.POINT_CLOUD], dtype=np.float32)),
                point_cloud_mask=np.asarray(context[features.POINT_CLOUD_MASK], dtype=np.float32),
                grasps=features.unflatten(features.GRASPS, np.asarray(context[features.GRASPS], dtype=np.float32)),
                grasps_mask=np.asarray(context[features.GRASPS_MASK], dtype=np.float32),
            )
        )
    if seed_range is not None:
        rule = f"scene seeds in [{seed_range[0]}, {seed_range[1]})"
    elif last_fraction is not None:
        rule = f"last {last_fraction:g} of the dataset's {len(set(scene_of.tolist()))} scenes (by seed)"
    else:
        rule = "all scenes of the dataset"
    return episodes, dict(rule=rule, scene_seeds=sorted(chosen), dataset_episodes=int(dataset.num_episodes))


def make_windows(episodes: Sequence[EpisodeData], history: int, horizon: int) -> list[tuple[int, int]]:
    """Every full window as ``(episode position in the list, current step)``:
    ``history - 1 <= t <= S - 1 - horizon``."""
    if history < 1 or horizon < 1:
        raise ValueError(f"history and horizon must be >= 1, got {history}, {horizon}")
    return [(i, t) for i, ep in enumerate(episodes) for t in range(history - 1, len(ep.states) - horizon)]


def _state_poses(states: np.ndarray) -> torch.Tensor:
    s = torch.as_tensor(states, dtype=torch.float64)
    return se3.pose_to_matrix(s[..., features.EE_POS], s[..., features.EE_QUAT])


def window_batch(
    episodes: Sequence[EpisodeData], windows: Sequence[tuple[int, int]], history: int, horizon: int
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """Policy batch, current poses ``(B, 4, 4)`` and recorded future poses ``(B, H, 4, 4)`` (float64, world)."""
    states, clouds, cloud_masks, grasps, grasp_masks, futures = [], [], [], [], [], []
    for i, t in windows:
        ep = episodes[i]
        states.append(ep.states[t - history + 1 : t + 1])
        futures.append(ep.states[t : t + horizon + 1])
        clouds.append(ep.point_cloud)
        cloud_masks.append(ep.point_cloud_mask)
        grasps.append(ep.grasps)
        grasp_masks.append(ep.grasps_mask)
    batch = {
        features.STATE: torch.as_tensor(np.stack(states), dtype=torch.float32),
        features.POINT_CLOUD: torch.as_tensor(np.stack(clouds)),
        features.POINT_CLOUD_MASK: torch.as_tensor(np.stack(cloud_masks)),
        features.GRASPS: torch.as_tensor(np.stack(grasps)),
        features.GRASPS_MASK: torch.as_tensor(np.stack(grasp_masks)),
    }
    poses = _state_poses(np.stack(futures))  # (B, H + 1, 4, 4)
    return batch, poses[:, 0], poses[:, 1:]


# ----------------------------------------------------------------------------- calibration

CALIBRATION_ALPHA = 0.85
"""The shared controller's OOD-gate quantile (docs/PAPER_DETAILS.md), used to check the prior's calibration."""


def step0_calibration(mixture: Any, true_translation: torch.Tensor,
                      alpha: float = CALIBRATION_ALPHA) -> dict[str, torch.Tensor]:
    """How well the step-0 translation Gaussians cover the expert's next translation velocity.

    Args:
        mixture: the prior's ``TwistMixture`` (B windows, K classes; m/s, EE body frame).
        true_translation: ``(B, 3)`` the recorded velocity of the next step (same frame and units).
    Returns per window ``(B,)``: ``maha_sq_ml`` the squared Mahalanobis distance under the most
    likely class; ``covered_ml`` / ``covered_any`` whether it is within ``chi2.ppf(alpha, 3)``
    of that class / of the nearest class (the latter is the shared controller's OOD test with a
    perfect user: a calibrated prior covers ~``alpha``); ``nll`` the mixture's negative
    log-likelihood (nats); ``sigma_ml`` the geometric-mean standard deviation of the ML class (m/s).
    """
    from rtv3_maniskill.shared_control import gaussians, ood_gate

    threshold = ood_gate.ood_threshold(alpha, 3)
    mu, cov = mixture.trans_mean.double(), mixture.trans_cov.double()
    true_v = true_translation.double()[:, None]  # (B, 1, 3) against K classes
    maha = gaussians.mahalanobis_sq(true_v, mu, cov)  # (B, K)
    log_n = gaussians.gaussian_log_prob(true_v, mu, cov)
    log_det = torch.linalg.slogdet(cov)[1]
    best = mixture.log_weights.argmax(-1)
    rows = torch.arange(best.shape[0])
    return dict(
        maha_sq_ml=maha[rows, best],
        covered_ml=maha[rows, best] <= threshold,
        covered_any=maha.min(-1).values <= threshold,
        nll=-torch.logsumexp(mixture.log_weights.double() + log_n, -1),
        sigma_ml=torch.exp(log_det[rows, best] / 6.0),
    )


# ----------------------------------------------------------------------------- evaluation


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
    from tqdm import tqdm

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
        from rtv3_maniskill.policies.rtv3.checkpoints import load_policy

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
