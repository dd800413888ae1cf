"""`rtv3 evaluate`: trajectory-prediction metrics (ADE/FDE, BoM/ML) and the closed-loop planning benchmark."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.benchmarks import (
    held_out_windows,
    outcomes,
    planning,
    planning_records,
    prediction,
    prediction_metrics,
)
from rtv3_maniskill.benchmarks.goals import GOAL_CHECKS
from rtv3_maniskill.benchmarks.planning_success import is_planning_success, planning_distance
from rtv3_maniskill.cli import main
from rtv3_maniskill.twist_mixture import TwistMixture

NUM_POINTS, MAX_GRASPS = 256, 16
GEN_ARGS = ["--num-points", str(NUM_POINTS), "--max-grasps", str(MAX_GRASPS), "--context", "mesh",
            "--scene-type", "packed"]


def _random_poses(shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    rot = se3.so3_exp(torch.randn(*shape, 3, generator=g, dtype=torch.float64))
    return se3.make_transform(rot, torch.randn(*shape, 3, generator=g, dtype=torch.float64) * 0.2)


def _offset(x: float = 0.0, rz: float = 0.0) -> torch.Tensor:
    """Body-frame offset: translation x (m) along the pose's own x axis, then a rotation rz about its z axis."""
    return se3.make_transform(se3.so3_exp(torch.tensor([0.0, 0.0, rz], dtype=torch.float64)),
                              torch.tensor([x, 0.0, 0.0], dtype=torch.float64))


# ----------------------------------------------------------------------------- prediction metrics


def test_metric_is_zero_for_a_perfect_prediction_and_scales_known_offsets():
    gt = _random_poses((4, 12))
    assert prediction_metrics.displacement_errors(gt, gt).abs().max() < 1e-9
    # A constant 1 cm offset along x (in the ground-truth frame: E = T_gt^-1 T_pred) costs 10.0 at every step.
    errors = prediction_metrics.displacement_errors(gt, gt @ _offset(x=0.01))
    torch.testing.assert_close(errors, torch.full((4, 12), 10.0, dtype=torch.float64))
    ade, fde = prediction_metrics.ade_fde(errors)
    torch.testing.assert_close(ade, torch.full((4,), 10.0, dtype=torch.float64))
    torch.testing.assert_close(fde, torch.full((4,), 10.0, dtype=torch.float64))
    # World-frame 1 cm shift of poses with identity rotation: the same 10.0.
    level = se3.make_transform(torch.eye(3, dtype=torch.float64).expand(3, 4, 3, 3),
                               torch.rand(3, 4, 3, dtype=torch.float64))
    shifted = level.clone()
    shifted[..., 0, 3] += 0.01
    torch.testing.assert_close(prediction_metrics.displacement_errors(level, shifted),
                               torch.full((3, 4), 10.0, dtype=torch.float64))
    # Rotation is weighted by 0.3/pi per rad (planning weights).
    rot_err = prediction_metrics.displacement_errors(gt, gt @ _offset(rz=0.1))
    torch.testing.assert_close(rot_err, torch.full((4, 12), 1000 * 0.3 / math.pi * 0.1, dtype=torch.float64))
    with pytest.raises(ValueError, match="NaN"):
        prediction_metrics.displacement_errors(gt, torch.full_like(gt, float("nan")))
    with pytest.raises(ValueError, match="4, 4"):
        prediction_metrics.displacement_errors(gt[..., :3, :], gt)


def test_best_of_mode_takes_the_minimum_most_likely_the_argmax_class():
    gt = _random_poses((1, 12), seed=1)
    # Mode 0: 2 cm off everywhere. Mode 1: exact, but the last step 5 cm off. Mode 2: 1 cm off, most likely.
    growing = gt[:, None].repeat(1, 3, 1, 1, 1)
    growing[:, 0] = gt @ _offset(x=0.02)
    growing[:, 1, -1] = gt[:, -1] @ _offset(x=0.05)
    growing[:, 2] = gt @ _offset(x=0.01)
    log_prior = torch.log(torch.tensor([[0.2, 0.1, 0.7]], dtype=torch.float64))
    m = prediction_metrics.mode_metrics(gt, growing, log_prior)
    torch.testing.assert_close(m["ade_bom"], torch.tensor([50.0 / 12], dtype=torch.float64))  # mode 1
    torch.testing.assert_close(m["fde_bom"], torch.tensor([10.0], dtype=torch.float64))  # mode 2: minimised separately
    torch.testing.assert_close(m["ade_ml"], torch.tensor([10.0], dtype=torch.float64))
    torch.testing.assert_close(m["fde_ml"], torch.tensor([10.0], dtype=torch.float64))
    # Most likely = mode 0 now: ML errors follow the prior, BoM does not.
    m0 = prediction_metrics.mode_metrics(gt, growing, log_prior[:, [2, 1, 0]])
    torch.testing.assert_close(m0["ade_ml"], torch.tensor([20.0], dtype=torch.float64))
    assert m0["ade_bom"] == m["ade_bom"] and bool((m0["ade_bom"] <= m0["ade_ml"]).all())
    with pytest.raises(ValueError, match=r"\(B, K\)"):
        prediction_metrics.mode_metrics(gt, growing, log_prior[:, :2])


def test_scene_seed_selection_rules():
    seeds = [5, 3, 3, 1, 2, 4]
    assert held_out_windows.select_scene_seeds(seeds, seed_range=(2, 4)) == [2, 3]
    assert held_out_windows.select_scene_seeds(seeds, last_fraction=0.2) == [5]  # ceil(0.2 * 5) = 1 scene
    assert held_out_windows.select_scene_seeds(seeds, last_fraction=0.5) == [3, 4, 5]
    assert held_out_windows.select_scene_seeds(seeds, all_scenes=True) == [1, 2, 3, 4, 5]
    assert held_out_windows.parse_seed_range("100:200") == (100, 200)
    with pytest.raises(ValueError, match="exactly one"):
        held_out_windows.select_scene_seeds(seeds)
    with pytest.raises(ValueError, match="exactly one"):
        held_out_windows.select_scene_seeds(seeds, seed_range=(0, 1), all_scenes=True)
    with pytest.raises(ValueError, match="no episode has a scene seed"):
        held_out_windows.select_scene_seeds(seeds, seed_range=(10, 20))
    with pytest.raises(ValueError, match=r"\(0, 1\]"):
        held_out_windows.select_scene_seeds(seeds, last_fraction=1.5)
    for bad in ("7", "a:b", "5:5"):
        with pytest.raises(ValueError, match="A:B|empty"):
            held_out_windows.parse_seed_range(bad)


# ----------------------------------------------------------------------------- fixtures: tiny dataset, untrained policy


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("eval") / "ds"
    assert main(["generate", "--num-scenes", "1", "--output", str(root), "--grasps-per-scene", "2", *GEN_ARGS]) == 0
    return root


@pytest.fixture(scope="module")
def untrained_policy(tmp_path_factory) -> Path:
    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("policy") / "pretrained_model"
    RTV3Policy(RTV3Config(device="cpu", num_points=NUM_POINTS, max_grasps=MAX_GRASPS)).save_pretrained(path)
    return path


@pytest.mark.sim
def test_ground_truth_poses_are_the_integrated_recorded_twists(tiny_dataset):
    """The recorded future poses equal the recorded twists integrated from the current pose (T Exp(a dt))."""
    episodes, held_out = held_out_windows.load_episodes(tiny_dataset, all_scenes=True)
    assert episodes and held_out["scene_seeds"] == [0]
    windows = held_out_windows.make_windows(episodes, features.HISTORY_STEPS, features.HORIZON_STEPS)
    assert len(windows) == sum(len(ep.states) - features.HISTORY_STEPS - features.HORIZON_STEPS + 1 for ep in episodes)
    batch, current, gt = held_out_windows.window_batch(episodes, windows[::7], features.HISTORY_STEPS,
                                                       features.HORIZON_STEPS)
    assert batch[features.STATE].shape == (len(windows[::7]), features.HISTORY_STEPS, features.STATE_DIM)
    # observation.state's twist at t+1 is the action realised over step t.
    twists = torch.stack(
        [torch.as_tensor(episodes[i].states[t + 1 : t + 1 + features.HORIZON_STEPS, features.EE_TWIST])
         for i, t in windows[::7]]
    )
    integrated = prediction_metrics.future_poses(current, twists)
    assert prediction_metrics.displacement_errors(gt, integrated).max() < 0.5  # < 0.5e-3 of pose distance


@pytest.mark.sim
def test_prediction_cli_reports_finite_consistent_metrics(tiny_dataset, untrained_policy, tmp_path, capsys):
    out = tmp_path / "prediction.json"
    args = ["evaluate", "prediction", "--policy.path", str(untrained_policy), "--dataset.root", str(tiny_dataset)]
    assert main([*args, "--scene-seeds", "0:1", "--output", str(out)]) == 0
    assert "Best-of-Mode" in capsys.readouterr().out
    report = json.loads(out.read_text())
    m = report["metrics"]
    assert all(math.isfinite(v) and v > 0 for v in m.values())
    assert m["ade_bom"] <= m["ade_ml"] + 1e-9 and m["fde_bom"] <= m["fde_ml"] + 1e-9
    episodes, _ = held_out_windows.load_episodes(tiny_dataset, all_scenes=True)
    assert report["num_windows"] == sum(len(ep.states) - 19 for ep in episodes)
    assert report["num_episodes"] == len(episodes) and report["scene_seeds"] == [0]
    assert report["window"] == dict(history=8, horizon=12, length=20, current_index=7)
    # Errors of the most likely trajectory grow along the horizon on average; ADE is their mean.
    per_step = report["per_step_ml"]
    assert len(per_step) == 12 and per_step[-1] > per_step[0]
    assert m["ade_ml"] == pytest.approx(sum(per_step) / 12) and m["fde_ml"] == pytest.approx(per_step[-1])
    # A capped, seeded subset of windows.
    capped = tmp_path / "capped.json"
    assert main([*args, "--all-scenes", "--max-windows", "5", "--output", str(capped)]) == 0
    assert json.loads(capped.read_text())["num_windows"] == 5
    with pytest.raises(SystemExit, match="no episode has a scene seed"):
        main([*args, "--scene-seeds", "1000:2000"])
    with pytest.raises(SystemExit):  # a held-out rule is required
        main(args)


@pytest.mark.sim
def test_prediction_refuses_a_policy_of_another_context_size(tiny_dataset, tmp_path):
    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
    from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy

    policy = RTV3Policy(RTV3Config(device="cpu", num_points=128, max_grasps=MAX_GRASPS))
    with pytest.raises(ValueError, match="N=256 points .* N=128"):
        prediction.run_prediction_evaluation(None, tiny_dataset, all_scenes=True, policy=policy, progress=False)
    with pytest.raises(SystemExit, match="no RT-V3 checkpoint"):
        main(["evaluate", "prediction", "--policy.path", str(tmp_path), "--dataset.root", str(tiny_dataset),
              "--all-scenes"])


# ----------------------------------------------------------------------------- planning: success rule


def test_planning_success_rule_uses_the_pregrasp_its_twin_and_threshold():
    grasps = _random_poses((3,), seed=3)
    pre = features.pregrasp_poses(grasps)
    # The pre-grasp is 5 cm back along the grasp's own approach (z) axis.
    torch.testing.assert_close(pre[:, :3, 3], grasps[:, :3, 3] - 0.05 * grasps[:, :3, 2])
    d = planning_distance(pre[0], grasps)
    assert d[0] < 1e-9 and d[1] > 0.05
    # Parallel-jaw twin: the pre-grasp rotated by pi about its z axis is the same goal.
    assert planning_distance(se3.rotate_about_z(pre[0], math.pi), grasps)[0] < 1e-9
    # Threshold 0.2 on L1 translation + (0.3/pi) * L1 Euler, strict.
    near = pre[0] @ _offset(x=0.19)
    assert planning_distance(near, grasps)[0] == pytest.approx(0.19)
    assert bool(is_planning_success(planning_distance(near, grasps)[0]))
    assert not bool(is_planning_success(planning_distance(pre[0] @ _offset(x=0.21), grasps)[0]))
    assert not bool(is_planning_success(0.2))
    # Rotation: pi/2 about z costs 0.3/pi * pi/2 = 0.15 (success); the twin is pi/2 away too.
    quarter = planning_distance(pre[0] @ _offset(rz=math.pi / 2), grasps)[0]
    assert quarter == pytest.approx(0.15) and bool(is_planning_success(quarter))
    # Under the shared-control weight (0.6/pi) the same pose would not count as reached (0.3 > 0.1): different rule.
    assert se3.pose_distance(pre[0], pre[0] @ _offset(rz=math.pi / 2),
                             se3.SHARED_CONTROL_ROT_WEIGHT) == pytest.approx(0.3)
    # Collision wins over success at the same step.
    assert outcomes.trial_outcome(collision=True, success=True) == "collision"
    assert outcomes.trial_outcome(collision=False, success=True) == "success"
    assert outcomes.trial_outcome(collision=False, success=False) is None


def test_context_mask_keeps_only_the_target():
    mask = torch.tensor([[1.0, 1.0, 1.0, 0.0]])
    assert features.context_mask(mask, 1, "target").tolist() == [[0.0, 1.0, 0.0, 0.0]]
    assert features.context_mask(mask, 1, "all").tolist() == mask.tolist()
    with pytest.raises(ValueError, match="not a valid candidate"):
        features.context_mask(mask, 3, "target")
    with pytest.raises(ValueError, match="unknown context mode"):
        features.context_mask(mask, 1, "nearest")


# ----------------------------------------------------------------------------- planning: closed loop


def _trial_rows(folder: Path, name: str = "planning_trials.csv") -> list[dict]:
    with open(folder / name, newline="") as f:
        return list(csv.DictReader(f))


def _goal_rows(folder: Path) -> list[dict]:
    return _trial_rows(folder, "planning_goals.csv")


@pytest.mark.sim
def test_planning_benchmark_runs_writes_and_resumes(untrained_policy, tmp_path, capsys):
    out = tmp_path / "planning"
    args = ["evaluate", "planning", "--policy.path", str(untrained_policy), "--scenes", "1",
            "--max-grasps-per-scene", "1", "--point-cloud", "mesh", "--scene-type", "packed", "--output", str(out)]
    assert main(args) == 0
    assert "SR" in capsys.readouterr().out
    rows = _trial_rows(out)
    assert len(rows) == 1 and rows[0]["outcome"] in outcomes.OUTCOMES
    assert int(rows[0]["context_grasps"]) == 1 and 1 <= int(rows[0]["steps"]) <= 150
    summary = json.loads((out / "planning_summary.json").read_text())
    assert summary["trials"] == 1
    assert summary["SR"] + summary["CR"] + summary["TOR"] == pytest.approx(1.0)
    # Rerun: the finished (scene, grasp) is skipped, no row is added, the summary is the same; paired
    # with itself, the run ties on its one trial.
    assert main([*args, "--compare-with", str(out)]) == 0
    assert "on the 1 trials both ran" in capsys.readouterr().out
    assert _trial_rows(out) == rows
    summary = json.loads((out / "planning_summary.json").read_text())
    assert summary["trials"] == 1
    assert (summary["paired_with"]["paired_trials"], summary["paired_with"]["wins"]) == (1, 0)
    with pytest.raises(SystemExit, match="other settings"):
        main([*args[:-2], "--context", "all", "--output", str(out)])
    # Every target carries the arm-reach check rtv3 benchmark-shared makes, and the summary splits on it; a
    # folder written before the check existed gains it on a rerun, with no trial run again.
    goal = _goal_rows(out)
    assert [(g["scene_seed"], g["grasp_index"]) for g in goal] == [(r["scene_seed"], r["grasp_index"]) for r in rows]
    assert goal[0]["check"] in GOAL_CHECKS and summary["goal_checks"] == {goal[0]["check"]: 1}
    assert summary["arm_reachable"]["trials"] == (goal[0]["check"] == "feasible")
    (out / "planning_goals.csv").unlink()
    (out / "planning_goals.settings.json").unlink()
    assert main(args) == 0
    assert "whose target the arm can reach" in capsys.readouterr().out
    assert _goal_rows(out) == goal and _trial_rows(out) == rows


class _PreGraspOracle:
    """Test controller: drives the TCP straight to the pre-grasp of the first grasp it is shown.

    It sees only what the benchmark gives the policy, so it also checks the target-only context.
    """

    def __init__(self) -> None:
        self.config = SimpleNamespace(num_points=NUM_POINTS, max_grasps=MAX_GRASPS)
        self.shown: set[int] = set()

    def reset(self) -> None:
        pass

    def select_action(self, obs: dict) -> torch.Tensor:
        visible = torch.nonzero(obs[features.GRASPS_MASK][0] > 0.5).flatten()
        self.shown.add(len(visible))
        g = obs[features.GRASPS][0, visible[0]].double()
        state = obs[features.STATE][0].double()
        tcp = se3.pose_to_matrix(state[features.EE_POS], state[features.EE_QUAT])
        pre = features.pregrasp_poses(se3.pose_to_matrix(g[:3], g[3:7]))
        twin = se3.rotate_about_z(pre, math.pi)
        goal = (pre if se3.so3_log(tcp[:3, :3].T @ pre[:3, :3]).norm()
                <= se3.so3_log(tcp[:3, :3].T @ twin[:3, :3]).norm() else twin)
        return (se3.body_twist(tcp, goal, 0.5)).float()[None]  # close the gap in ~0.5 s (speed-limited)


@pytest.mark.sim
def test_a_controller_that_reaches_the_pregrasp_counts_as_success(tmp_path):
    oracle = _PreGraspOracle()
    config = planning.PlanningConfig(output=tmp_path / "oracle", scenes=1, max_grasps_per_scene=1, point_cloud="mesh",
                                     scene_type="packed")
    summary = planning.run_planning_benchmark(config, policy=oracle, progress=False)
    row = _trial_rows(tmp_path / "oracle")[0]
    assert oracle.shown == {1}  # only the target grasp was visible
    assert summary["success"] == 1 and row["outcome"] == "success", row
    assert int(row["reached_grasp"]) == int(row["grasp_index"]) and float(row["final_distance"]) < 0.2
    assert int(row["steps"]) < 150


def test_planning_trials_resume_after_a_torn_row_and_summary_leaves_out_missing_starts(tmp_path):
    trials = planning_records.trials_store(tmp_path, {"seed": 9})
    base = dict(start_distance="0.5", final_distance="0.1", min_distance="0.1", reached_grasp=2, context_grasps=1,
                start_attempts=1, wall_time_s="1.0")
    trials.append(dict(base, scene_seed=7, grasp_index=2, outcome="success", steps=40))
    trials.append(dict(base, scene_seed=7, grasp_index=3, outcome="no_start_pose", steps=0))
    trials.close()
    path = tmp_path / "planning_trials.csv"
    with open(path, "a") as f:
        f.write("7,4,collis")  # killed mid-write
    resumed = planning_records.trials_store(tmp_path, {"seed": 9})
    assert (7, 2) in resumed and (7, 3) in resumed and (7, 4) not in resumed
    resumed.append(dict(base, scene_seed=7, grasp_index=4, outcome="timeout", steps=150))
    resumed.close()
    rows = planning_records.read_trials(path)
    assert [(int(r["grasp_index"]), r["outcome"]) for r in rows] == [(2, "success"), (3, "no_start_pose"),
                                                                     (4, "timeout")]
    summary = planning_records.summarize(rows)
    assert summary["trials"] == 2 and summary["no_start_pose"] == 1
    assert (summary["SR"], summary["CR"], summary["TOR"]) == (0.5, 0.0, 0.5)
    assert summary["mean_steps_success"] == 40.0
    with pytest.raises(ValueError, match="other settings"):
        planning_records.trials_store(tmp_path, {"seed": 10})


def test_two_runs_are_paired_on_the_trials_both_ran(tmp_path):
    base = dict(start_distance="0.5", final_distance="0.1", min_distance="0.1", reached_grasp=0, context_grasps=1,
                start_attempts=1, wall_time_s="1.0", steps=40)
    settings = dict(seed=8, scene_type="packed_ycb", policy_path="/ckpt/shipped", planner="policy")

    def run(folder, outcomes, **changed):
        trials = planning_records.trials_store(tmp_path / folder, dict(settings, **changed))
        for (scene, grasp), outcome in outcomes.items():
            trials.append(dict(base, scene_seed=scene, grasp_index=grasp, outcome=outcome))
        trials.close()
        return planning_records.read_trials(tmp_path / folder / "planning_trials.csv")

    # Trials (1, g): the new run wins 0-3 and loses 4; 5 and 6 agree; (2, 0) has no start pose in the
    # baseline and (3, 0) only the new run ran: neither counts.
    shipped = {(1, g): "success" if g >= 4 else "collision" for g in range(7)} | {(2, 0): "no_start_pose"}
    new = {(1, g): "success" if g != 4 else "timeout" for g in range(7)} | {(2, 0): "success", (3, 0): "success"}
    run("shipped", shipped)
    mine = dict(settings, policy_path="/ckpt/new")  # another checkpoint: the one setting that may differ
    planning_records.check_baseline(tmp_path / "shipped", mine)
    paired = planning_records.paired_with_baseline(run("new", new, policy_path="/ckpt/new"), tmp_path / "shipped")
    assert (paired["paired_trials"], paired["wins"], paired["losses"]) == (7, 4, 1)
    assert (paired["SR"], paired["baseline_SR"]) == pytest.approx((6 / 7, 3 / 7))
    assert paired["mcnemar_p"] == pytest.approx(2 * (1 + 5) / 32)  # two-sided exact: P(X <= 1 | n = 5, 1/2) x 2
    with pytest.raises(FileNotFoundError, match="no planning_trials.csv"):
        planning_records.check_baseline(tmp_path / "missing", mine)
    # The same seeds on another preset are other scenes: refused, naming the setting.
    with pytest.raises(ValueError, match="scene_type: 'packed_ycb' there, 'mixed' here"):
        planning_records.check_baseline(tmp_path / "shipped", dict(mine, scene_type="mixed"))
    with pytest.raises(ValueError, match="no trial in common"):
        planning_records.paired_with_baseline(run("other_scenes", {(9, 0): "success"}), tmp_path / "shipped")


def test_step0_calibration_of_a_known_gaussian():
    """Samples of the ML class's own Gaussian are covered at the chi2 rate; far points are not."""
    b, k = 4000, 2
    gen = torch.Generator().manual_seed(0)
    axes = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))[0]
    cov = axes @ torch.diag(torch.tensor([0.01, 0.02, 0.05], dtype=torch.float64) ** 2) @ axes.T
    mean = torch.tensor([[0.1, 0.0, -0.05], [-0.3, 0.2, 0.0]], dtype=torch.float64)
    mixture = TwistMixture(
        log_weights=torch.log(torch.tensor([0.7, 0.3], dtype=torch.float64)).expand(b, k),
        trans_mean=mean.expand(b, k, 3),
        trans_cov=cov.expand(b, k, 3, 3),
        rotation_given_translation=lambda v: (torch.zeros_like(v), torch.eye(3).expand(*v.shape[:-1], 3, 3)),
    )
    samples = mean[0] + torch.randn(b, 3, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(cov).T
    cal = prediction_metrics.step0_calibration(mixture, samples, alpha=0.85)
    assert abs(float(cal["covered_ml"].double().mean()) - 0.85) < 0.03
    assert abs(float(cal["sigma_ml"][0]) - (0.01 * 0.02 * 0.05) ** (1 / 3)) < 1e-9
    far = prediction_metrics.step0_calibration(mixture, torch.full((b, 3), 5.0, dtype=torch.float64))
    assert not bool(far["covered_any"].any()) and bool((far["nll"] > cal["nll"].max()).all())


@pytest.mark.sim
def test_neoss_planner_drives_straight_through_the_damper(tmp_path):
    # Table I's NeoSS row: no policy; a straight twist to the target's pre-grasp, tracked by the NEO
    # QP whose collision damper keeps the arm out of the scene.
    config = planning.PlanningConfig(output=tmp_path / "neoss", scenes=1, max_grasps_per_scene=1, point_cloud="mesh",
                                     scene_type="packed", planner="neoss")
    summary = planning.run_planning_benchmark(config, progress=False)
    row = _trial_rows(tmp_path / "neoss")[0]
    assert summary["trials"] == 1 and row["outcome"] in ("success", "collision", "timeout")
    assert summary["settings"]["planner"] == "neoss" and summary["collision"] == 0
    with pytest.raises(ValueError, match="unknown planner"):
        planning.PlanningConfig(output=tmp_path, planner="rrt")
