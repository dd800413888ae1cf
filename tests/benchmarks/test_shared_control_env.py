"""SharedControlEnv, run_episode and the shared-control benchmark on the real GraspClutter-v1 (CPU)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from rtv3_maniskill.benchmarks.episodes import EpisodeResult, SharedControlEnv, run_episode
from rtv3_maniskill.benchmarks.shared_config import BenchmarkConfig, BenchmarkError
from rtv3_maniskill.benchmarks.shared_merge import merge_runs
from rtv3_maniskill.benchmarks.shared_report import summary_markdown
from rtv3_maniskill.benchmarks.shared_results import results_store
from rtv3_maniskill.benchmarks.shared_runner import run_benchmark
from rtv3_maniskill.benchmarks.shared_statistics import (
    oracle_gain_share,
    paired_with_baseline,
    success_by_goal_check,
    summarize,
)
from rtv3_maniskill.policies.rtv3 import load_policy
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy
from rtv3_maniskill.shared_control import DirectTeleoperation, SharedControlConfig, SharedController, make_user
from rtv3_maniskill.shared_control.methods import make_method
from rtv3_maniskill.shared_control.shared_controller import MODES
from rtv3_maniskill.shared_control.simulated_users import IdealUser

N_POINTS = 512
MAX_LINEAR, MAX_ANGULAR = 0.3, 1.2  # the pd_ee_twist controller's limits
LIMITS = (MAX_LINEAR, MAX_ANGULAR)


@pytest.fixture(scope="module")
def env():
    e = SharedControlEnv(num_points=N_POINTS)
    yield e
    e.close()


@pytest.fixture(scope="module")
def policy():
    torch.manual_seed(0)
    return RTV3Policy(RTV3Config(device="cpu", num_points=N_POINTS)).eval()


class HistorySpy:
    """The real policy, recording whether each query advanced its observation history."""

    def __init__(self, policy):
        self.policy, self.config, self.pushes = policy, policy.config, []

    def predict_step0_mixture(self, observation, update_history=True):
        self.pushes.append(update_history)
        return self.policy.predict_step0_mixture(observation, update_history=update_history)

    def predict_action_chunk(self, observation, update_history=True):
        self.pushes.append(update_history)
        return self.policy.predict_action_chunk(observation, update_history=update_history)

    def reset(self):
        self.pushes = []
        self.policy.reset()


def _pregrasp_offset() -> torch.Tensor:
    """``(4, 4)`` float64: a grasp pose times this is its pre-grasp (5 cm back along the tool z)."""
    offset = torch.eye(4, dtype=torch.float64)
    offset[2, 3] = -0.05
    return offset


def _within_limits(twist: torch.Tensor) -> bool:
    return bool(twist[:3].norm() <= MAX_LINEAR + 1e-6 and twist[3:].norm() <= MAX_ANGULAR + 1e-6)


@pytest.mark.sim
def test_direct_passes_the_user_twist_through(env):
    env.method = make_method("direct", LIMITS)
    env.reset(seed=2)
    command = torch.tensor([0.08, -0.04, 0.06, 0.3, -0.2, 0.4], dtype=torch.float64)
    realised = []
    for _ in range(12):
        obs, _, _, _, info = env.step(command)
        torch.testing.assert_close(info["robot_twist"], command, atol=1e-7, rtol=1e-7)
        assert torch.equal(info["user_twist"], command)
        assert info["assistance_mode"] == "user_only"
        realised.append(obs["extra"]["tcp_twist"][0])
    # The TCP moves with the user's twist (after the first steps of acceleration).
    np.testing.assert_allclose(torch.stack(realised[3:]).median(0).values.numpy(), command.numpy(), atol=0.01)


@pytest.mark.sim
def test_ho_assists_towards_the_grasp_goals(env):
    env.method = make_method("ho", LIMITS)
    env.reset(seed=5)
    count = int(env.base.grasps_mask[0].sum())
    user = make_user("noisy", seed=1)
    user.reset(env.user_goal())
    for step in range(5):
        _, _, _, _, info = env.step(user(env.base.tcp_pose_matrix[0]))
        twist = info["robot_twist"]
        assert torch.isfinite(twist).all() and _within_limits(twist)
        belief = info["assistance"]["belief"]
        assert belief.shape == (count,) and abs(belief.sum() - 1) < 1e-9
        if step == 0:  # one goal per valid grasp (its pre-grasp + the pre-grasp's twin)
            assert env.method.episodes[0].num_goals == count
            assert env.method.episodes[0].targets.shape == (2 * count, 4, 4)
            torch.testing.assert_close(env.method.episodes[0].targets[:count],
                                       env.base.grasp_poses[0, :count].double() @ _pregrasp_offset(), atol=1e-5, rtol=0)
        assert 0.0 <= info["assistance"]["target_belief"] <= 1.0
    # No user input: HO still moves the robot (the assistance alone).
    _, _, _, _, info = env.step(None)
    assert info["robot_twist"].norm() > 1e-4 and torch.equal(info["user_twist"], torch.zeros(6, dtype=torch.float64))


@pytest.mark.sim
def test_rtv3_shared_control_twists_and_diagnostics(env, policy):
    spy = HistorySpy(policy)
    env.method = SharedController(spy, SharedControlConfig(max_linear_speed=MAX_LINEAR, max_angular_speed=MAX_ANGULAR))
    env.reset(seed=2)  # the TCP starts > 7 cm from every object: autonomy allowed
    user = make_user("noisy", seed=2)
    user.reset(env.user_goal())
    seen = set()
    for step in range(8):
        before = len(spy.pushes)
        command = None if step % 2 else user(env.base.tcp_pose_matrix[0])
        _, _, _, _, info = env.step(command)
        diag = info["assistance"]
        assert diag["mode"] in MODES
        seen.add(diag["mode"])
        twist = info["robot_twist"]
        assert twist.shape == (6,) and torch.isfinite(twist).all() and _within_limits(twist)
        assert abs(diag["class_weights"].sum() - 1) < 1e-6
        assert diag["trans_entropy_lower"] <= diag["trans_entropy_upper"]
        assert diag["rot_entropy_lower"] <= diag["rot_entropy_upper"]
        # The policy's observation history advances exactly once per control step.
        assert sum(spy.pushes[before:]) == 1, spy.pushes[before:]
    assert "autonomous" in seen and "shared" in seen, seen


@pytest.mark.sim
def test_run_episode_ideal_user_direct_reaches_the_pregrasp(env):
    # The highest pre-grasp of the scene: a clear approach from the start pose.
    env.reset(seed=5)
    base = env.base
    count = int(base.grasps_mask[0].sum())
    target = int((base.grasp_poses[0, :count] @ _pregrasp_offset().float())[:, 2, 3].argmax())
    result = run_episode(env, DirectTeleoperation(*LIMITS), make_user("ideal"), max_steps=150, seed=5,
                         options=dict(target_grasp_index=target))
    assert result.success, f"final distance {result.final_distance:.3f}"
    assert 0 < result.steps < 150 and result.final_distance < 0.1
    assert result.trajectory.shape == (result.steps + 1, 4, 4) and len(result.diagnostics) == result.steps
    assert int(base.target_grasp_index[0]) == target
    # The same seed reloads the same scene and start: the episode is reproducible.
    again = run_episode(env, DirectTeleoperation(*LIMITS), make_user("ideal"), max_steps=150, seed=5,
                        options=dict(target_grasp_index=target))
    assert again.steps == result.steps
    np.testing.assert_allclose(again.trajectory, result.trajectory, atol=1e-5)


class DivingUser(IdealUser):
    """An ideal user whose goal is the pre-grasp's orientation 30 cm below the table: it drives into the scene."""

    def reset(self, goal_pose):
        goal = torch.as_tensor(goal_pose, dtype=torch.float64).clone()
        goal[2, 3] = -0.3
        super().reset(goal)


@pytest.mark.sim
def test_run_episode_can_end_a_trial_at_the_first_contact(env):
    options = dict(target_grasp_index=0)
    going_on = run_episode(env, DirectTeleoperation(*LIMITS), DivingUser(), max_steps=60, seed=5, options=options)
    contacts = [d["collision"] for d in going_on.diagnostics]
    assert any(contacts) and going_on.collision and going_on.outcome == "collision"
    first = contacts.index(True) + 1  # steps up to and including the first contact
    assert going_on.steps == 60 > first

    stopped = run_episode(env, DirectTeleoperation(*LIMITS), DivingUser(), max_steps=60, seed=5, options=options,
                          stop_on_contact=True)
    assert stopped.steps == first and stopped.outcome == "collision" and not stopped.success
    assert stopped.contact and set(stopped.contact.split("+")) <= {"table", "object"}  # it dives, arm stretched
    assert [d["collision"] for d in stopped.diagnostics] == [False] * (first - 1) + [True]
    # Identical up to the contact (the contact step itself is solved with contact state left by the
    # previous episode, so it may differ by a fraction of a millimetre).
    np.testing.assert_allclose(stopped.trajectory[:first], going_on.trajectory[:first], atol=1e-5)
    np.testing.assert_allclose(stopped.trajectory[first], going_on.trajectory[first], atol=2e-3)


@pytest.mark.parametrize("success, collision, outcome", [
    (True, False, "success"), (True, True, "collision"), (False, True, "collision"), (False, False, "timeout"),
])
def test_a_contact_fails_the_trial_even_where_the_pregrasp_was_reached(success, collision, outcome):
    result = EpisodeResult(success=success, collision=collision, steps=10, trajectory=np.zeros((11, 4, 4)),
                           diagnostics=[])
    assert result.outcome == outcome


def test_summary_outcomes_add_up_to_the_trials():
    rows = [dict(scene_seed=900000, grasp_index=i, user="noisy", method="direct", outcome=o, success=r, collision=c,
                 steps=n)
            for i, (o, r, c, n) in enumerate([("success", 1, 0, 40), ("success", 1, 0, 60), ("collision", 1, 1, 30),
                                              ("collision", 0, 1, 12), ("timeout", 0, 0, 150)])]
    (s,) = summarize(rows)
    assert (s["trials"], s["SR"], s["CR"], s["TOR"], s["reached"]) == (5, 40.0, 40.0, 20.0, 60.0)
    assert s["mean_iterations"] == 50.0  # successful trials only
    assert "| noisy | Direct | 5 | 40.0 | 40.0 | 20.0 | 60.0 | 50.0 |" in summary_markdown([s])


def test_methods_are_paired_with_direct_and_tested_by_exact_mcnemar():
    # 10 goals: the oracle wins 8 (Direct failed, it succeeded) and loses 2; both succeed on none
    # else. Exact two-sided McNemar: 2 * P(X <= 2 | n = 10, 1/2) = 2 * (1 + 10 + 45) / 1024.
    rows = []
    for g in range(10):
        oracle_wins = g < 8
        rows.append(dict(scene_seed=1, grasp_index=g, user="noisy", method="direct",
                         outcome="timeout" if oracle_wins else "success", success=int(not oracle_wins), collision=0,
                         steps=150 if oracle_wins else 50))
        rows.append(dict(scene_seed=1, grasp_index=g, user="noisy", method="oracle",
                         outcome="success" if oracle_wins else "collision", success=int(oracle_wins),
                         collision=int(not oracle_wins), steps=60))
    direct, oracle = summarize(rows)
    assert direct["wins"] is None
    assert (oracle["paired_trials"], oracle["wins"], oracle["losses"]) == (10, 8, 2)
    assert oracle["mcnemar_p"] == pytest.approx(2 * (1 + 10 + 45) / 1024)
    assert "| noisy | Oracle | 10 | 80.0 |" in summary_markdown([direct, oracle])
    assert "8 / 2 | 0.109 |" in summary_markdown([direct, oracle])

    # Behind a safety filter the baseline is Direct behind the same filter: here Direct w. NeoSS
    # succeeds wherever the oracle w. NeoSS does, so the filter's gain is not the oracle's.
    filtered = [dict(row, method=row["method"] + "+neoss", outcome="success") for row in rows]
    by_method = {s["method"]: s for s in summarize(rows + filtered)}
    assert by_method["direct+neoss"]["wins"] is None
    assert (by_method["oracle+neoss"]["paired_trials"], by_method["oracle+neoss"]["wins"],
            by_method["oracle+neoss"]["losses"]) == (10, 0, 0)
    assert (by_method["oracle"]["wins"], by_method["oracle"]["losses"]) == (8, 2)


def test_summary_pairs_each_method_with_rtv3_when_it_ran():
    # 6 goals: the copilot succeeds on goals 0-2, RT-V3 on goals 2-5 -> copilot W / L vs RT-V3 = 2 / 3;
    # behind NeoSS the copilot is paired with RT-V3 behind NeoSS, never with the unfiltered RT-V3.
    def row(g, method, ok):
        return dict(scene_seed=1, grasp_index=g, user="noisy", method=method, outcome="success" if ok else "timeout",
                    success=int(ok), collision=0, steps=50 if ok else 150)

    rows = [row(g, "copilot", g < 3) for g in range(6)] + [row(g, "rtv3", g >= 2) for g in range(6)]
    rows += [row(g, "copilot+neoss", True) for g in range(6)] + [row(g, "rtv3+neoss", g == 0) for g in range(6)]
    versus = paired_with_baseline(rows, baseline="rtv3")
    assert set(versus) == {("noisy", "copilot"), ("noisy", "copilot+neoss")}
    assert (versus[("noisy", "copilot")]["wins"], versus[("noisy", "copilot")]["losses"]) == (2, 3)
    assert (versus[("noisy", "copilot+neoss")]["wins"], versus[("noisy", "copilot+neoss")]["losses"]) == (5, 0)
    text = summary_markdown(summarize(rows), versus_rtv3=versus)
    assert "| noisy | Copilot | 6 | 2 / 3 | 1 |" in text
    assert "| noisy | Copilot w. NeoSS | 6 | 5 / 0 | 0.0625 |" in text
    assert "paired with RT-V3" not in summary_markdown(summarize(rows))  # nothing to pair with: no section

def test_share_of_the_oracles_gain_is_computed_on_the_goals_all_three_ran():
    # 20 goals: Direct succeeds on 10, the oracle on 18, RT-V3 on 14 -> share (14 - 10) / (18 - 10) = 50 %.
    # A 21st goal only RT-V3 ran does not count; the laggy user's oracle is level with Direct: no share.
    def row(g, user, method, ok):
        return dict(scene_seed=1, grasp_index=g, user=user, method=method, outcome="success" if ok else "timeout",
                    success=int(ok), collision=0, steps=50 if ok else 150)

    rows = [row(g, "noisy", "direct", g < 10) for g in range(20)]
    rows += [row(g, "noisy", "oracle", g < 18) for g in range(20)]
    rows += [row(g, "noisy", "rtv3", g < 14) for g in range(21)]
    rows += [row(g, "laggy", m, True) for g in range(5) for m in ("direct", "oracle", "rtv3")]
    shares = oracle_gain_share(rows, resamples=500)
    assert set(shares) == {("noisy", "rtv3")}
    s = shares[("noisy", "rtv3")]
    assert (s["goals"], s["baseline_SR"], s["SR"], s["ceiling_SR"]) == (20, 50.0, 70.0, 90.0)
    assert s["share"] == pytest.approx(0.5)
    assert s["share_low"] < 0.5 < s["share_high"] <= 1.0  # RT-V3 never beats the oracle on these goals
    # The interval is the same with another method's rows beside (a merged folder, a part of one).
    with_ho = rows + [row(g, "noisy", "ho", g < 12) for g in range(20)]
    assert oracle_gain_share(with_ho, resamples=500)[("noisy", "rtv3")] == s
    by_method = {(x["user"], x["method"]): x for x in summarize(rows)}
    assert by_method[("noisy", "rtv3")]["oracle_gain_share"] == pytest.approx(0.5)
    assert by_method[("laggy", "rtv3")]["oracle_gain_share"] is None
    assert "| noisy | RT-V3 | 50 |" in summary_markdown(list(by_method.values()))


def test_success_is_split_by_the_goals_arm_reach_check():
    # Goals 0-3 pass the arm-reach check, 4-5 have no IK at the pre-grasp, goal 6 has no check (left out).
    checks = {(1, g): "feasible" for g in range(4)} | {(1, 4): "no_ik_pregrasp", (1, 5): "no_ik_pregrasp"}
    rows = [dict(scene_seed=1, grasp_index=g, user="noisy", method="direct", outcome="success" if ok else "timeout",
                 success=int(ok), collision=0, steps=50)
            for g, ok in enumerate([True, True, True, False, True, False, True])]
    by_check = success_by_goal_check(rows, checks)
    assert by_check == {("noisy", "direct"): {"feasible": (4, 75.0), "no_ik_pregrasp": (2, 50.0)}}
    text = summary_markdown(summarize(rows), by_check=by_check)
    assert "| User | Method | feasible | no_ik_pregrasp |" in text
    assert "| noisy | Direct | 75.0 (4) | 50.0 (2) |" in text
    # With one check only (the rule `reachable` runs feasible goals alone) there is nothing to split.
    assert "arm-reach check (trials" not in summary_markdown(summarize(rows[:4]),
                                                             by_check=success_by_goal_check(rows[:4], checks))


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.sim
def test_benchmark_in_worker_processes_gives_the_serial_results_and_resumes_either_way(tmp_path):
    common = dict(scenes=2, users=["noisy"], methods=["direct"], seed=3, goals_per_scene=1, max_steps=30)
    run_benchmark(BenchmarkConfig(output=tmp_path / "serial", **common), progress=False)
    run_benchmark(BenchmarkConfig(output=tmp_path / "parallel", **common), progress=False, workers=2)

    def trials(folder):
        return sorted((r["scene_seed"], r["grasp_index"], r["outcome"], r["steps"], r["user_seed"])
                      for r in _rows(folder / "results.csv"))

    assert len(trials(tmp_path / "serial")) == 2
    assert trials(tmp_path / "parallel") == trials(tmp_path / "serial")
    assert sorted(map(str.split, (tmp_path / "parallel" / "goals.csv").read_text().splitlines())) == sorted(
        map(str.split, (tmp_path / "serial" / "goals.csv").read_text().splitlines()))
    # A serial rerun of the parallel folder, with one more method, runs only that method's trials.
    run_benchmark(BenchmarkConfig(output=tmp_path / "parallel", **{**common, "methods": ["direct", "ho"]}),
                  progress=False)
    methods = [r["method"] for r in _rows(tmp_path / "parallel" / "results.csv")]
    assert sorted(methods) == ["direct", "direct", "ho", "ho"]
    with pytest.raises(BenchmarkError, match="workers"):
        run_benchmark(BenchmarkConfig(output=tmp_path / "serial", **common), progress=False, workers=0)


@pytest.mark.sim
def test_benchmark_writes_results_and_resumes_without_duplicates(tmp_path):
    config = BenchmarkConfig(output=tmp_path, scenes=1, users=["noisy"], methods=["direct", "ho"], seed=3,
                             goals_per_scene=1, max_steps=40)
    summary = run_benchmark(config, progress=False)
    rows = _rows(tmp_path / "results.csv")
    assert [r["method"] for r in rows] == ["direct", "ho"]
    assert all(r["outcome"] in ("success", "collision", "timeout") for r in rows)
    assert len({(r["scene_seed"], r["grasp_index"], r["user"], r["method"]) for r in rows}) == 2
    assert [(s["user"], s["method"], s["trials"]) for s in summary] == [("noisy", "direct", 1), ("noisy", "ho", 1)]
    for name in ("summary.csv", "summary.md", "success_rates.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert "| noisy | HO | 1 |" in (tmp_path / "summary.md").read_text()

    # Simulate an interrupted run: the last trial's row is torn (half written). It is not a result:
    # the rerun runs that trial again and writes it whole.
    lines = (tmp_path / "results.csv").read_text().splitlines(keepends=True)
    (tmp_path / "results.csv").write_text("".join(lines[:-1]) + lines[-1][: len(lines[-1]) // 2])
    run_benchmark(config, progress=False)
    again = _rows(tmp_path / "results.csv")
    assert [(r["grasp_index"], r["method"]) for r in again] == [(r["grasp_index"], r["method"]) for r in rows]
    assert again[-1]["success"] == rows[-1]["success"] and again[-1]["steps"] == rows[-1]["steps"]
    run_benchmark(config, progress=False)  # nothing left to do
    assert len(_rows(tmp_path / "results.csv")) == 2

    changed = BenchmarkConfig(output=tmp_path, scenes=1, users=["noisy"], methods=["direct"], seed=3,
                              goals_per_scene=1, max_steps=60)
    with pytest.raises(BenchmarkError, match="other settings"):
        run_benchmark(changed, progress=False)


def _finished_run(folder, config, rows):
    """A benchmark output folder as ``run_benchmark`` leaves it: ``config.json`` + ``results.csv``."""
    folder.mkdir()
    with results_store(folder, config.fingerprint(None)) as store:
        for r in rows:
            store.append({k: r.get(k, 0) for k in store.fields})


def _row(scene, method, outcome, steps):
    return dict(scene_seed=scene, grasp_index=3, user="laggy", method=method, outcome=outcome,
                success=int(outcome == "success"), collision=int(outcome == "collision"), steps=steps)


def test_runs_split_over_processes_merge_into_one_summary(tmp_path):
    config = BenchmarkConfig(output=tmp_path / "unused", scenes=2, users=["laggy"], methods=["direct"])
    _finished_run(tmp_path / "direct", config, [_row(900000, "direct", "success", 30),
                                                _row(900001, "direct", "collision", 12)])
    _finished_run(tmp_path / "ho", config, [_row(900000, "ho", "timeout", 150), _row(900001, "ho", "success", 50)])
    summary = merge_runs([tmp_path / "direct", tmp_path / "ho"], tmp_path / "all")
    assert [(s["method"], s["trials"], s["SR"], s["CR"], s["TOR"]) for s in summary] == [
        ("direct", 2, 50.0, 50.0, 0.0), ("ho", 2, 50.0, 0.0, 50.0)]
    assert len(_rows(tmp_path / "all" / "results.csv")) == 4
    assert "| laggy | HO | 2 |" in (tmp_path / "all" / "summary.md").read_text()

    with pytest.raises(BenchmarkError, match="choose a new --output"):
        merge_runs([tmp_path / "direct", tmp_path / "ho"], tmp_path / "all")
    with pytest.raises(BenchmarkError, match="in both"):
        merge_runs([tmp_path / "direct", tmp_path / "direct"], tmp_path / "twice")
    other = BenchmarkConfig(output=tmp_path / "unused", scenes=2, users=["laggy"], methods=["ho"], max_steps=100)
    _finished_run(tmp_path / "ho100", other, [_row(900000, "ho", "success", 40)])
    with pytest.raises(BenchmarkError, match="max_steps"):
        merge_runs([tmp_path / "direct", tmp_path / "ho100"], tmp_path / "mixed")
    with pytest.raises(BenchmarkError, match="config.json is missing"):
        merge_runs([tmp_path / "direct", tmp_path / "nowhere"], tmp_path / "lost")


def _started_rtv3_benchmark(tmp_path, weights: bytes):
    """A checkpoint folder holding ``weights`` and an RT-V3 benchmark output folder started with it."""
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    (ckpt / "model.safetensors").write_bytes(weights)
    config = BenchmarkConfig(output=tmp_path / "out", scenes=1, methods=["rtv3"])
    _finished_run(config.output, config, [])
    with results_store(config.output, config.fingerprint(ckpt)) as store:  # one finished trial
        store.append({k: v for k, v in _row(900000, "rtv3", "success", 30).items()} | {"wall_time_s": 1.0})
    return ckpt, config


def test_benchmark_refuses_to_resume_with_other_weights_at_the_same_path(tmp_path):
    ckpt, config = _started_rtv3_benchmark(tmp_path, b"old weights")
    results_store(config.output, config.fingerprint(ckpt)).close()  # same weights: resumes
    (ckpt / "model.safetensors").write_bytes(b"new weights")  # retrained in place
    with pytest.raises(BenchmarkError, match="policy_weights_sha256"):
        results_store(config.output, config.fingerprint(ckpt))


def test_benchmark_refuses_to_resume_with_other_shared_control_settings(tmp_path):
    ckpt, default = _started_rtv3_benchmark(tmp_path, b"weights")
    assert default.fingerprint(ckpt)["shared_control"]["ood_covariance"] == "predictive"  # the tuned fusion
    paper = BenchmarkConfig(output=default.output, scenes=1, methods=["rtv3"], fusion="paper",
                            shared_control={"uncommanded_axes": "missing_unused"})
    settings = paper.shared_control_config(0.3, 1.2)
    assert ((settings.ood_covariance, settings.belief_memory, settings.uncommanded_axes)
            == ("class", 0.0, "missing_unused"))
    with pytest.raises(BenchmarkError, match="shared_control"):
        results_store(paper.output, paper.fingerprint(ckpt))
    with pytest.raises(BenchmarkError, match="bad shared_control settings"):
        BenchmarkConfig(output=tmp_path, shared_control={"ood_covariance": "user"})
    with pytest.raises(BenchmarkError, match="bad shared_control settings"):
        BenchmarkConfig(output=tmp_path, shared_control={"no_such_field": 1})
    with pytest.raises(BenchmarkError, match="speed limits come from the env"):
        BenchmarkConfig(output=tmp_path, shared_control={"max_linear_speed": 1.0})


@pytest.mark.sim
def test_bad_inputs_give_clear_errors(env, policy, tmp_path):
    with pytest.raises(ValueError, match="unknown simulated user"):
        make_user("telepath")
    with pytest.raises(ValueError, match="unknown assistance method"):
        make_method("teleport", LIMITS)
    with pytest.raises(ValueError, match="needs a policy"):
        make_method("rtv3", LIMITS)
    with pytest.raises(BenchmarkError, match="unknown simulated user 'telepath'"):
        BenchmarkConfig(output=tmp_path, users=["telepath"])
    with pytest.raises(BenchmarkError, match="unknown assistance method 'teleport'"):
        BenchmarkConfig(output=tmp_path, methods=["direct", "teleport"])
    with pytest.raises(FileNotFoundError, match="--policy.path"):
        load_policy(tmp_path)

    env.method = make_method("direct", LIMITS)
    env.reset(seed=2)
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.tensor([0.1, float("nan"), 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(7))
    # A policy made for another cloud size than the env's.
    other = RTV3Policy(RTV3Config(device="cpu", num_points=256))
    env.method = make_method("rtv3", LIMITS, policy=other)
    with pytest.raises(ValueError, match="num_points"):
        env.reset(seed=2)


def test_cli_reports_bad_options_and_missing_checkpoint(tmp_path):
    from rtv3_maniskill.cli import main

    with pytest.raises(SystemExit, match="unknown simulated user 'telepath'"):
        main(["benchmark-shared", "--users", "noisy,telepath", "--output", str(tmp_path / "b")])
    with pytest.raises(SystemExit, match="no RT-V3 checkpoint"):
        main(["demo", "--policy.path", str(tmp_path / "missing"), "--output", str(tmp_path / "d")])


@pytest.mark.sim
def test_neoss_safety_filter_keeps_a_diving_user_out_of_the_scene():
    # The same user drives into the table: with Direct alone the trial ends in a contact; behind the
    # NEO damper the arm stops short of it. The benchmark names such results METHOD+neoss.
    options = dict(target_grasp_index=0)
    plain = SharedControlEnv(num_points=N_POINTS)
    hit = run_episode(plain, DirectTeleoperation(*LIMITS), DivingUser(), max_steps=60, seed=5, options=options)
    plain.close()
    assert hit.collision
    safe = SharedControlEnv(num_points=N_POINTS, safety_filter="neoss")
    assert safe.base.control_mode == "pd_ee_twist_qp"
    kept = run_episode(safe, DirectTeleoperation(*LIMITS), DivingUser(), max_steps=60, seed=5, options=options)
    safe.close()
    assert not kept.collision and kept.outcome == "timeout" and kept.qp_infeasible_steps == 0
    assert kept.trajectory[-1][2, 3] > 0.0  # the TCP stays above the table top
    with pytest.raises(ValueError, match="unknown safety filter"):
        SharedControlEnv(num_points=N_POINTS, safety_filter="bumper")


def test_an_output_folder_of_another_version_is_refused(tmp_path):
    """A results.csv with other columns, or a config.json without a setting the run records, is refused
    with one message naming the difference (a run, its command and a merge alike)."""
    import json

    from rtv3_maniskill.benchmarks.shared_results import RESULT_FIELDS
    from rtv3_maniskill.cli import main

    config = BenchmarkConfig(output=tmp_path / "old_columns", scenes=1, users=["laggy"], methods=["direct"])
    _finished_run(config.output, config, [_row(900000, "direct", "success", 30)])
    _finished_run(tmp_path / "ho", config, [_row(900000, "ho", "success", 40)])
    fields = RESULT_FIELDS[:-1]  # a file written before the twist_deviation column
    row = dict(_row(900000, "direct", "collision", 30), wall_time_s=1.0)
    (config.output / "results.csv").write_text(",".join(fields) + "\n" + ",".join(str(row.get(k, 0)) for k in fields)
                                               + "\n")
    with pytest.raises(BenchmarkError, match="has the columns .* expected .*'twist_deviation'"):
        run_benchmark(config, progress=False)
    with pytest.raises(SystemExit, match="^error: .*has the columns"):
        main(["benchmark-shared", "--scenes", "1", "--users", "laggy", "--methods", "direct",
              "--output", str(config.output)])
    with pytest.raises(BenchmarkError, match="has the columns"):
        merge_runs([config.output, tmp_path / "ho"], tmp_path / "merged")

    settings = json.loads((tmp_path / "ho" / "config.json").read_text())
    del settings["goals"]  # a setting an older version did not record
    (tmp_path / "ho" / "config.json").write_text(json.dumps(settings))
    with pytest.raises(BenchmarkError, match="other settings .*goals: None -> 'reachable'"):
        run_benchmark(BenchmarkConfig(output=tmp_path / "ho", scenes=1, users=["laggy"], methods=["ho"]),
                      progress=False)


@pytest.mark.sim
def test_trials_start_at_the_ready_pose_and_infeasible_goals_are_never_run(tmp_path, env):
    from rtv3_maniskill.benchmarks.shared_results import GOAL_FIELDS
    from rtv3_maniskill.benchmarks.shared_runner import trial_options
    from rtv3_maniskill.records import RecordStore
    from rtv3_maniskill.robot.panda_model import PandaKinematics
    from rtv3_maniskill.robot.scene_geometry import READY_QPOS

    # Scene 800000 has candidates without collision-free IK at the pre-grasp or with a blocked approach.
    config = BenchmarkConfig(output=tmp_path, scenes=1, seed=8, users=["ideal"], methods=["direct"], max_steps=2)
    run_benchmark(config, progress=False)
    checks = {int(r["grasp_index"]): r["check"] for r in RecordStore.read(tmp_path / "goals.csv", GOAL_FIELDS)}
    infeasible = {g for g, c in checks.items() if c != "feasible"}
    assert infeasible, "the scene was chosen for an infeasible candidate"
    run = {int(r["grasp_index"]) for r in _rows(tmp_path / "results.csv")}
    assert run == set(checks) - infeasible
    assert "infeasible, never run" in (tmp_path / "summary.md").read_text()
    # Every trial resets the arm to the ready pose.
    result = run_episode(env, DirectTeleoperation(*LIMITS), make_user("ideal"), max_steps=1, seed=800000,
                         options=trial_options(min(run)))
    ready = PandaKinematics().forward_kinematics(READY_QPOS)
    np.testing.assert_allclose(result.trajectory[0], ready, atol=2e-3)
