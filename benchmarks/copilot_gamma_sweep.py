"""The copilot's gamma sweep on the validation block: SR and distance from the user's command against gamma.

Usage: ``python benchmarks/copilot_gamma_sweep.py [--output outputs/val/copilot_sweep]
[--gammas 0.1,0.2,0.4,0.6,0.8,1.0] [--scenes 20] [--goals-per-scene 4] [--users noisy,single_dof]
[--copilot-path DIR] [--workers 1]``

Runs ``rtv3 benchmark-shared --preset paper --seed 8`` (the validation block; 9 is the test block) once
with Direct and RT-V3 and once per gamma with the copilot, every run on the same scenes, goals and user
noise, each in its own folder under ``--output`` (rerun the same command to resume). Then it prints, per
gamma and user, SR, wins / losses against Direct on the same trials and the mean twist deviation
(``results.csv``'s ``twist_deviation``: how far the executed twist is from the user's), writes
``sweep.csv`` and ``sweep.png`` (SR and deviation against gamma, Direct and RT-V3 as reference lines), and
names the gamma with the best SR over the users (ties: the smaller gamma, closer to the user).
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from rtv3_maniskill.benchmarks.shared_results import result_rows  # noqa: E402
from rtv3_maniskill.shared_control.copilot import SHIPPED_COPILOT  # noqa: E402


def _run(output: Path, args: argparse.Namespace, methods: str, extra: list[str]) -> list[dict[str, str]]:
    cmd = [sys.executable, "-m", "rtv3_maniskill.cli", "benchmark-shared", "--preset", "paper", "--seed", "8",
           "--scenes", str(args.scenes), "--goals-per-scene", str(args.goals_per_scene), "--users", args.users,
           "--methods", methods, "--workers", str(args.workers), "--output", str(output), *extra]
    print(" ".join(cmd[2:]), flush=True)
    subprocess.run(cmd, check=True)
    return result_rows(output / "results.csv")


def _by_trial(rows: list[dict[str, str]], method: str) -> dict[tuple[str, str, str], dict[str, str]]:
    return {(r["scene_seed"], r["grasp_index"], r["user"]): r for r in rows if r["method"] == method}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=Path("outputs/val/copilot_sweep"))
    parser.add_argument("--gammas", default="0.1,0.2,0.4,0.6,0.8,1.0")
    parser.add_argument("--scenes", type=int, default=20)
    parser.add_argument("--goals-per-scene", type=int, default=4)
    parser.add_argument("--users", default="noisy,single_dof")
    parser.add_argument("--copilot-path", default=str(SHIPPED_COPILOT))
    parser.add_argument("--copilot-steps", type=int, default=None, help="DDIM steps of the whole schedule")
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args(argv)
    try:
        gammas = sorted(float(g) for g in args.gammas.split(",") if g.strip())
    except ValueError:
        parser.error(f"--gammas: not a comma-separated list of numbers: {args.gammas!r}")
    users = [u.strip() for u in args.users.split(",") if u.strip()]

    base = _run(args.output / "base", args, "direct,rtv3", [])
    direct, rtv3 = _by_trial(base, "direct"), _by_trial(base, "rtv3")
    copilot_flags = ["--copilot-path", args.copilot_path]
    if args.copilot_steps is not None:
        copilot_flags += ["--copilot-steps", str(args.copilot_steps)]
    table = []
    for method, rows in (("direct", direct), ("rtv3", rtv3)):
        for user in users:
            trials = [r for k, r in rows.items() if k[2] == user]
            table.append(dict(method=method, gamma="", user=user, trials=len(trials),
                              sr=100 * np.mean([int(r["success"]) for r in trials]), wins="", losses="",
                              deviation=np.mean([float(r["twist_deviation"]) for r in trials])))
    for gamma in gammas:
        rows = _by_trial(_run(args.output / f"gamma_{gamma:g}", args, "copilot",
                              [*copilot_flags, "--copilot-gamma", str(gamma)]), "copilot")
        for user in users:
            keys = [k for k in rows if k[2] == user and k in direct]
            wins = sum(int(rows[k]["success"]) > int(direct[k]["success"]) for k in keys)
            losses = sum(int(rows[k]["success"]) < int(direct[k]["success"]) for k in keys)
            table.append(dict(method="copilot", gamma=gamma, user=user, trials=len(keys),
                              sr=100 * np.mean([int(rows[k]["success"]) for k in keys]), wins=wins, losses=losses,
                              deviation=np.mean([float(rows[k]["twist_deviation"]) for k in keys])))

    with open(args.output / "sweep.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, list(table[0]))
        writer.writeheader()
        writer.writerows({**r, "sr": f"{r['sr']:.1f}", "deviation": f"{r['deviation']:.4f}"} for r in table)
    print(f"{'method':8s} {'gamma':>5s} {'user':12s} {'n':>4s} {'SR %':>6s} {'W / L vs Direct':>16s} {'deviation':>9s}")
    for r in table:
        wl = f"{r['wins']} / {r['losses']}" if r["method"] == "copilot" else ""
        print(f"{r['method']:8s} {r['gamma']!s:>5s} {r['user']:12s} {r['trials']:4d} {r['sr']:6.1f} {wl:>16s} "
              f"{r['deviation']:9.3f}")
    mean_sr = {g: np.mean([r["sr"] for r in table if r["gamma"] == g]) for g in gammas}
    best = max(gammas, key=lambda g: (round(mean_sr[g], 6), -g))
    print(f"best gamma on validation (mean SR over {', '.join(users)}): {best:g} ({mean_sr[best]:.1f} %)")

    fig, (ax_sr, ax_dev) = plt.subplots(1, 2, figsize=(10, 4))
    for i, user in enumerate(users):
        color = f"C{i}"
        rows = [r for r in table if r["method"] == "copilot" and r["user"] == user]
        ax_sr.plot(gammas, [r["sr"] for r in rows], "o-", color=color, label=f"copilot, {user}")
        ax_dev.plot(gammas, [r["deviation"] for r in rows], "o-", color=color, label=f"copilot, {user}")
        for method, style in (("direct", ":"), ("rtv3", "--")):
            ref = next(r for r in table if r["method"] == method and r["user"] == user)
            ax_sr.axhline(ref["sr"], color=color, ls=style, lw=1, label=f"{method}, {user}")
            ax_dev.axhline(ref["deviation"], color=color, ls=style, lw=1)
    ax_sr.set(xlabel="gamma (noising fraction)", ylabel="SR %", title="success rate (validation, paper preset)")
    ax_dev.set(xlabel="gamma (noising fraction)", ylabel="mean |robot twist - user twist|",
               title="distance from the user's command")
    ax_sr.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.output / "sweep.png", dpi=120)
    print(f"wrote {args.output / 'sweep.csv'} and {args.output / 'sweep.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
