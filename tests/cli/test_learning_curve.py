"""`rtv3 learning-curve`: the campaign's stages in training order, paired with the reference, the best stage."""

from __future__ import annotations

import csv
import json

import torch
from safetensors.torch import save_file

from rtv3_maniskill.benchmarks.campaign_curve import reference_lines
from rtv3_maniskill.benchmarks.planning_records import TRIAL_FIELDS
from rtv3_maniskill.benchmarks.shared_results import RESULT_FIELDS
from rtv3_maniskill.cli import main

TRIALS = [(800000 + i // 2, i % 2) for i in range(10)]  # (scene_seed, grasp_index) of each of 10 trials


def _csv(path, fields, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, restval="0")
        writer.writeheader()
        writer.writerows(rows)


def _planning(folder, successes):
    """A planning run whose first ``successes`` of TRIALS succeed."""
    outcomes = ["success" if i < successes else "collision" for i in range(len(TRIALS))]
    _csv(folder / "planning_trials.csv", TRIAL_FIELDS,
         [dict(scene_seed=s, grasp_index=g, outcome=o, wall_time_s=1) for (s, g), o in zip(TRIALS, outcomes)])
    sr = successes / len(TRIALS)
    (folder / "planning_summary.json").write_text(json.dumps(dict(trials=len(TRIALS), SR=sr, CR=1 - sr, TOR=0.0)))


def _shared(folder, succeeded: dict[tuple[str, str], list[int]]):
    """A benchmark-shared run: per (user, method), the indices of TRIALS that succeed."""
    rows = [dict(scene_seed=s, grasp_index=g, user=user, method=method, wall_time_s=1,
                 outcome="success" if i in wins else "timeout")
            for (user, method), wins in succeeded.items() for i, (s, g) in enumerate(TRIALS)]
    _csv(folder / "results.csv", RESULT_FIELDS, rows)
    (folder / "summary.csv").write_text("user,method\n")


def _stage(out, name, episodes, step, sr, cr, shared=None):
    folder = out / name
    (folder / "cache").mkdir(parents=True)
    (folder / "cache" / "summary.json").write_text(json.dumps(dict(episodes=episodes, frames=10 * episodes)))
    (folder / "run" / "checkpoints" / "last").mkdir(parents=True)
    save_file({"train_step": torch.tensor(step)}, str(folder / "run" / "checkpoints" / "last" / "model.safetensors"))
    (folder / "planning").mkdir()
    (folder / "planning" / "planning_summary.json").write_text(
        json.dumps(dict(trials=200, SR=sr, CR=cr, TOR=1 - sr - cr)))
    if shared is not None:
        _shared(folder / "shared", shared)


def test_stages_in_training_order_and_the_best_by_sr_then_fewer_collisions(tmp_path, capsys):
    _stage(tmp_path, "long", 10000, 30000, 0.79, 0.10)
    _stage(tmp_path, "dagger_1", 9000, 14000, 0.80, 0.10)
    _stage(tmp_path, "demos_10", 8000, 12000, 0.80, 0.08)
    _stage(tmp_path, "demos_2", 5000, 10000, 0.745, 0.15)
    _stage(tmp_path, "dagger_2", 9500, 16000, 0.70, 0.12)  # a round after a later chunk
    _stage(tmp_path, "demos_11", 10000, 18000, 0.70, 0.12)
    (tmp_path / "demos_3").mkdir()  # not evaluated yet: left out
    assert main(["learning-curve", str(tmp_path)]) == 0
    with open(tmp_path / "curve.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["stage"] for r in rows] == ["demos_2", "demos_10", "dagger_1", "dagger_2", "demos_11", "long"]
    assert [r["model_step"] for r in rows] == ["10000", "12000", "14000", "16000", "18000", "30000"]
    assert (tmp_path / "curve.png").stat().st_size > 0
    capsys.readouterr()
    assert main(["learning-curve", str(tmp_path), "--best"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "demos_10" / "run" / "checkpoints" / "last")


def test_stages_are_paired_with_the_reference_and_the_best_counts_the_rtv3_rows(tmp_path, capsys):
    _planning(tmp_path / "reference" / "planning", successes=5)
    _shared(tmp_path / "reference" / "shared", {("noisy", "direct"): [0, 1], ("noisy", "rtv3"): [0, 1, 2, 3],
                                                 ("single_dof", "direct"): [0], ("single_dof", "rtv3"): [0, 5]})
    # demos_1 plans best but helps the users less than dagger_1 does: the mean of the three SRs picks dagger_1.
    _stage(tmp_path, "demos_1", 1000, 6000, 0.7, 0.3,
           {("noisy", "rtv3"): [0], ("single_dof", "rtv3"): [0]})
    _stage(tmp_path, "dagger_1", 2000, 10000, 0.6, 0.4,
           {("noisy", "rtv3"): [0, 1, 2, 3, 4, 5, 6], ("single_dof", "rtv3"): [0, 1, 2, 3, 4]})
    _stage(tmp_path, "demos_2", 3000, 14000, 0.9, 0.1)  # no RT-V3 rows yet: does not compete for --best
    _planning(tmp_path / "dagger_1" / "planning", successes=6)
    assert main(["learning-curve", str(tmp_path)]) == 0
    with open(tmp_path / "curve.csv", newline="") as f:
        rows = {r["stage"]: r for r in csv.DictReader(f)}
    # dagger_1: trials 0-5 succeed in planning where the reference's 0-4 do; RT-V3 paired with the reference's RT-V3.
    assert (rows["dagger_1"]["wins"], rows["dagger_1"]["losses"]) == ("1", "0")
    assert float(rows["dagger_1"]["noisy_SR"]) == 0.7
    assert (rows["dagger_1"]["noisy_wins"], rows["dagger_1"]["noisy_losses"]) == ("3", "0")
    assert (rows["dagger_1"]["single_dof_wins"], rows["dagger_1"]["single_dof_losses"]) == ("4", "1")
    assert (rows["demos_1"]["noisy_wins"], rows["demos_1"]["noisy_losses"]) == ("0", "3")
    assert rows["demos_2"]["noisy_SR"] == ""
    capsys.readouterr()
    assert main(["learning-curve", str(tmp_path), "--best"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "dagger_1" / "run" / "checkpoints" / "last")


def test_the_reference_lines_hold_its_rate_on_the_reachable_targets(tmp_path):
    _planning(tmp_path / "reference" / "planning", successes=5)
    assert reference_lines(tmp_path) == {"planning": 0.5}  # a run from before the arm-reach check
    summary = tmp_path / "reference" / "planning" / "planning_summary.json"
    summary.write_text(json.dumps(dict(json.loads(summary.read_text()), arm_reachable=dict(trials=8, SR=0.625))))
    assert reference_lines(tmp_path) == {"planning": 0.5, "planning_reachable": 0.625}


def test_a_folder_without_an_evaluated_stage_is_an_error(tmp_path):
    assert main(["learning-curve", str(tmp_path)]) == 1
    assert main(["learning-curve", str(tmp_path / "missing")]) == 1
