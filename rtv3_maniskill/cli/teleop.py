"""``rtv3 teleop``: grasp objects in clutter by keyboard, gamepad or a simulated user, with shared control.

Keyboard (the pygame window must have the focus): ``w/s a/d q/e`` move the hand along world x, y, z;
``i/k j/l u/o`` rotate it; ``f`` approach (the paper's Y), ``g`` grasp (A), ``t`` lift (X),
``r`` release (B); F12 saves a screenshot; Esc quits. Gamepad: see ``teleop/devices.py``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rtv3_maniskill.cli import UsageError
from rtv3_maniskill.cli.scene_args import (
    add_fusion_argument,
    add_push_argument,
    add_scene_arguments,
    check_push_argument,
    fusion_name,
    policy_path,
    push_if_asked,
    scene_settings,
)
from rtv3_maniskill.records import claim_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--method", default="rtv3",
                        help="assistance method: rtv3, direct, ho or copilot (the ones told nothing of the target)")
    parser.add_argument("--copilot-path", type=Path, default=None,
                        help="--method copilot: its diffusion policy (rtv3 train-copilot; default: the shipped one)")
    parser.add_argument("--copilot-gamma", type=float, default=None,
                        help="--method copilot: its noising fraction in [0, 1] (default: its validated one)")
    parser.add_argument("--input", default="keyboard",
                        help="keyboard, gamepad or simulated:NAME (NAME: ideal, noisy, laggy, mode_switching, ...)")
    parser.add_argument("--scene-seed", type=int, default=0, help="scene of the first trial (trial i: seed + i)")
    parser.add_argument("--trials", type=int, default=1, help="trials in this session")
    parser.add_argument("--participant", default="P0", help="participant id written with every trial")
    parser.add_argument("--record", type=Path, default=None,
                        help="record the session as a LeRobot dataset into this new folder (+ sessions.csv)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the session recorded in --record (same options) with its next trial")
    add_push_argument(parser, "the recorded session (--record)")
    parser.add_argument("--timeout", type=float, default=90.0, help="seconds of simulated time per trial")
    parser.add_argument("--headless", action="store_true", help="no window (simulated input only)")
    parser.add_argument("--realtime", choices=["auto", "on", "off"], default="auto",
                        help="pace at 20 Hz (auto: on for a person, off for a simulated user)")
    add_scene_arguments(parser, default_preset="paper")
    add_fusion_argument(parser)
    parser.add_argument("--safety-filter", choices=["neoss"], default=None,
                        help="put the NEO collision damper (NeoSS) between the assistance and the arm, as "
                             "benchmark-shared --safety-filter does; recorded sessions name it (method rtv3+neoss)")
    parser.add_argument("--target-grasp", type=int, default=None, help="target grasp index (default: drawn)")
    parser.add_argument("--policy.path", dest="policy_path", type=Path, default=None,
                        help="RT-V3 checkpoint folder (config.json + model.safetensors) or Hub repo id; "
                             "default: the scene preset's")
    parser.add_argument("--user-seed", type=int, default=0, help="seed of a simulated user's randomness")
    parser.add_argument("--screenshot", type=Path, default=None, help="PNG written by F12 (or at --screenshot-step)")
    parser.add_argument("--screenshot-step", type=int, default=None, help="save --screenshot after this many steps")


def run(args: argparse.Namespace) -> int:
    from rtv3_maniskill.shared_control.methods import UNINFORMED_METHODS, method_spec
    from rtv3_maniskill.shared_control.simulated_users import USERS
    from rtv3_maniskill.teleop.grasp_trial import TrialConfig
    from rtv3_maniskill.teleop.session import SessionConfig, TeleopSession

    if args.trials < 1:
        raise UsageError(f"--trials must be >= 1, got {args.trials}")
    if not args.timeout > 0:
        raise UsageError(f"--timeout must be a positive number of seconds, got {args.timeout}")
    kind, _, user = args.input.strip().lower().partition(":")
    if kind not in ("keyboard", "gamepad", "simulated") or (kind == "simulated") != bool(user):
        raise UsageError(f"--input {args.input!r}: expected keyboard, gamepad or simulated:NAME")
    if kind == "simulated" and user not in USERS:
        raise UsageError(f"--input {args.input!r}: unknown simulated user {user!r}; known: {', '.join(sorted(USERS))}")
    if kind == "gamepad":  # before the scene is built: a missing pad is found in a second
        from rtv3_maniskill.teleop.inputs import GamepadInput

        try:
            GamepadInput()
        except RuntimeError as err:
            raise SystemExit(f"error: --input gamepad: {err}") from None
    if args.method not in UNINFORMED_METHODS:
        raise UsageError(f"--method {args.method!r}: expected one of {', '.join(UNINFORMED_METHODS)}")
    if method_spec(args.method).needs_policy:
        from rtv3_maniskill.policies.rtv3.checkpoints import CheckpointError, resolve_checkpoint

        try:
            resolve_checkpoint(policy_path(args))
        except CheckpointError as err:
            raise SystemExit(f"error: {err}") from None
    copilot = None
    if args.method == "copilot":
        from rtv3_maniskill.shared_control.copilot import CopilotSettings

        given = dict(path=args.copilot_path and str(args.copilot_path), gamma=args.copilot_gamma)
        try:
            copilot = CopilotSettings(**{k: v for k, v in given.items() if v is not None})
        except ValueError as err:
            raise UsageError(f"--copilot-gamma: {err}") from None
    elif args.copilot_path is not None or args.copilot_gamma is not None:
        raise UsageError("--copilot-path and --copilot-gamma are for --method copilot")
    if args.headless and not args.input.startswith("simulated:"):
        raise SystemExit(f"error: --headless needs a simulated input (--input simulated:NAME), got {args.input!r}")
    if args.push_to_hub is not None and args.record is None:
        raise UsageError("--push-to-hub needs --record DIR (the session to push)")
    check_push_argument(args)
    if args.resume and args.record is None:
        raise UsageError("--resume needs --record DIR (the session to continue)")
    if args.record is not None and args.record.exists() and not args.resume:
        raise SystemExit(f"error: {args.record} already exists; record each session into a new folder, or continue "
                         "it with --resume")
    if args.resume:  # one writer per session folder: a second resume stops before the scene is built
        claim_folder(args.record)
    config = SessionConfig(
        method=args.method, input=args.input, scene_seed=args.scene_seed, trials=args.trials,
        participant=args.participant, record=args.record, resume=args.resume, headless=args.headless,
        realtime=None if args.realtime == "auto" else args.realtime == "on", policy_path=policy_path(args),
        **scene_settings(args), fusion=fusion_name(args), target_grasp=args.target_grasp,
        user_seed=args.user_seed, safety_filter=args.safety_filter, copilot=copilot,
        screenshot=args.screenshot, screenshot_step=args.screenshot_step,
        trial_config=TrialConfig(timeout_s=args.timeout),
    )
    try:
        session = TeleopSession(config)
    except (FileNotFoundError, ValueError, RuntimeError) as err:  # checkpoint, gamepad, display
        raise SystemExit(f"error: {str(err).strip().splitlines()[0]}") from None
    results = session.run()
    if session.interrupted:
        print("interrupted: the trials finished so far are kept" + (f" in {args.record}" if args.record else ""),
              file=sys.stderr)
        return 130
    counts: dict[str, int] = {}
    for r in results:
        counts[r.outcome] = counts.get(r.outcome, 0) + 1
    print("outcomes: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    if args.record is not None:
        print(f"recorded {len(results)} trial(s) into {args.record} (LeRobot dataset + sessions.csv)")
    push_if_asked(args, args.record, "Shared-control teleoperation trials (user twist, assistance and the executed "
                  "twist per step; sessions.csv has each trial's outcome)")
    return 0
