"""The `rtv3 teleop` loop's achieved control and display rates, Direct and RT-V3, with the window.

Runs simulated noisy-user trials paced at 20 Hz (`--realtime on`, as for a person) in a real pygame
window (under Xvfb when no DISPLAY is set) and prints, per method, the median over trials of the
control rate (steps / wall time) and the display rate (frames shown / wall time).

    python benchmarks/benchmark_teleop.py --trials 3 --timeout 15
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys


def _under_xvfb(argv: list[str]) -> int:
    """Run this script with ``argv`` on a private Xvfb display; the server stops after the run has exited
    (an X client whose server goes first ends with an X I/O error)."""
    read, write = os.pipe()
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "1024x600x24", "-nolisten", "tcp"],
                            pass_fds=(write,), stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as f:
        display = ":" + f.readline().strip()
    try:
        return subprocess.run([sys.executable, __file__, *argv], env=dict(os.environ, DISPLAY=display)).returncode
    finally:
        xvfb.terminate()
        xvfb.wait(timeout=10)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=3, help="trials per method (scenes 0..trials-1)")
    parser.add_argument("--timeout", type=float, default=15.0, help="simulated seconds per trial")
    parser.add_argument("--methods", default="direct,rtv3")
    args = parser.parse_args(argv)
    if not os.environ.get("DISPLAY"):
        return _under_xvfb(sys.argv[1:] if argv is None else argv)
    from rtv3_maniskill.teleop.grasp_trial import TrialConfig
    from rtv3_maniskill.teleop.session import SessionConfig, TeleopSession

    for method in args.methods.split(","):
        rates: dict[str, list[float]] = {"control_hz": [], "display_hz": []}
        session = TeleopSession(SessionConfig(method=method, input="simulated:noisy", trials=1, realtime=True,
                                              trial_config=TrialConfig(timeout_s=args.timeout)))
        try:
            for trial in range(args.trials):
                session.run_trial(trial)
                for key in rates:
                    rates[key].append(session.rates[key])
        finally:
            session.close()
        print(f"{method:7s} control {statistics.median(rates['control_hz']):5.1f} Hz   display "
              f"{statistics.median(rates['display_hz']):5.1f} Hz   (median of {args.trials} trials of "
              f"{args.timeout:g} s; per trial control {[round(r, 1) for r in rates['control_hz']]})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
