"""``rtv3 demo``: the main job. RT-V3 shared control of a simulated user in one clutter scene.

Loads the RT-V3 checkpoint, draws one ``GraspClutter-v1`` scene (``--seed``) and lets a simulated
user (``--user``, default ``mode_switching``, pausing 10 steps after every 20) drive towards the
episode's target pre-grasp with RT-V3 assistance for up to 150 steps (7.5 s at 20 Hz). Writes
``OUTPUT/demo.mp4`` (direct teleoperation and RT-V3 side by side, same user and noise, rendered;
skipped with a note when no Vulkan device can render) and ``OUTPUT/demo.png`` (class weights and
entropy bounds over time, autonomous phases shaded, distance to the goal), and prints both outcomes.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rtv3_maniskill.cli.scene_args import (
    add_fusion_argument,
    add_scene_arguments,
    fusion_name,
    policy_path,
    scene_settings,
)

if TYPE_CHECKING:
    import numpy as np

MODE_COLORS = {"autonomous": ("0.55", 0.30, "autonomous (prior's most likely action)"),
               "user_only": ("tab:red", 0.12, "user only (OOD / near the surface)")}


def _pauses(text: str) -> tuple[int, int]:
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 2 or not all(p.isdigit() for p in parts) or int(parts[0]) < 1:
        raise argparse.ArgumentTypeError(f"expected C,R (command steps >= 1, rest steps >= 0), got {text!r}")
    return int(parts[0]), int(parts[1])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy.path", dest="policy_path", type=Path, default=None,
                        help="RT-V3 checkpoint folder (config.json + model.safetensors) or Hub repo id; "
                             "default: the scene preset's")
    parser.add_argument("--seed", type=int, default=900000,
                        help="scene seed (same seed, same scene and target); default: the first scene of the test "
                             "block, with its own target draw (not picked for a result)")
    parser.add_argument("--user", default="mode_switching",
                        help="simulated user: noisy, laggy, mode_switching, single_dof, low_dof or ideal")
    parser.add_argument("--user-seed", type=int, default=0, help="seed of the user's randomness")
    parser.add_argument("--pauses", type=_pauses, default=(20, 10), metavar="C,R",
                        help="the user pauses: C steps of commands, then R steps of none, repeated "
                             "(RT-V3 acts on its own while the user rests: asynchronous autonomy); "
                             "default 20,10; 20,0 = never pauses")
    parser.add_argument("--target-grasp", type=int, default=None,
                        help="index of the target grasp (default: the episode's own draw)")
    parser.add_argument("--max-steps", type=int, default=150, help="control steps (20 Hz)")
    add_scene_arguments(parser, default_preset="paper")
    parser.add_argument("--output", type=Path, default=Path("outputs/demo"), help="folder for demo.mp4 and demo.png")
    parser.add_argument("--no-video", action="store_true", help="skip rendering the video")
    add_fusion_argument(parser)
    parser.add_argument("--safety-filter", choices=["neoss"], default=None,
                        help="put the NEO collision damper in front of both methods (the paper's 'w. NeoSS')")


def _make_env(want_video: bool, env_kwargs: dict[str, Any]):
    """A SharedControlEnv that renders if it can; returns (env, can_render)."""
    from rtv3_maniskill.benchmarks.episodes import SharedControlEnv

    if want_video:
        env = None
        try:
            # The scene cloud comes from the depth camera, as in the training data (`rtv3 generate`).
            env = SharedControlEnv(render_mode="rgb_array", rendered_context=True, **env_kwargs)
            env.reset(seed=0)
            env.render()
            return env, True
        except Exception as err:  # noqa: BLE001  (any renderer failure: go on without video)
            print(f"note: no video: rendering failed ({type(err).__name__}: {str(err).strip()[:200]}); "
                  f"a Vulkan device is needed (see README: lavapipe on CPU machines)")
            if env is not None:
                env.close()
    try:
        return SharedControlEnv(rendered_context=True, **env_kwargs), False
    except Exception:  # noqa: BLE001  (no render device at all: physics only, mesh-sampled cloud)
        return SharedControlEnv(render_backend="none", **env_kwargs), False


def _goal_pixels(env) -> np.ndarray | None:
    """Pixels ``(2, 2)`` of the target pre-grasp and grasp positions in the render camera (None if behind it)."""
    import numpy as np

    base = env.base
    cameras = getattr(base.scene, "human_render_cameras", {})
    if not cameras:
        return None
    params = next(iter(cameras.values())).get_params()
    extrinsic = params["extrinsic_cv"][0].double().cpu().numpy()
    intrinsic = params["intrinsic_cv"][0].double().cpu().numpy()
    points = np.stack([env.user_goal().numpy()[:3, 3], base.target_grasp_pose[0, :3, 3].double().cpu().numpy()])
    cam = points @ extrinsic[:, :3].T + extrinsic[:, 3]
    if (cam[:, 2] <= 0).any():
        return None
    uv = cam @ intrinsic.T
    return uv[:, :2] / uv[:, 2:]


def _annotate(frames: list, diagnostics: list[dict], label: str, goal_px=None) -> list:
    """Write the method, time and assistance mode onto every frame and mark the goal (PIL)."""
    import numpy as np
    from PIL import Image, ImageDraw

    from rtv3_maniskill.features import DT

    out = []
    for i, frame in enumerate(frames):
        image = Image.fromarray(np.ascontiguousarray(frame))
        draw = ImageDraw.Draw(image)
        if goal_px is not None:
            (u0, v0), (u1, v1) = goal_px
            draw.line([(u0, v0), (u1, v1)], fill=(255, 220, 0), width=2)  # approach: pre-grasp -> grasp
            draw.ellipse([u0 - 5, v0 - 5, u0 + 5, v0 + 5], outline=(255, 220, 0), width=2)
        mode = diagnostics[i - 1]["mode"] if i > 0 else "start"
        draw.rectangle([0, 0, image.width, 18], fill=(0, 0, 0))
        draw.text((6, 3), f"{label}  t={i * DT:4.2f}s  mode: {mode}   (yellow: target pre-grasp -> grasp)",
                  fill=(255, 255, 255))
        out.append(np.asarray(image))
    return out


def _side_by_side(left: list, right: list) -> list:
    """Frames of two runs next to each other, the shorter run holding its last frame."""
    import numpy as np

    count = max(len(left), len(right))
    return [np.concatenate([left[min(i, len(left) - 1)], right[min(i, len(right) - 1)]], axis=1) for i in range(count)]


def _spans(modes: list[str], wanted: str) -> list[tuple[int, int]]:
    """Half-open step ranges [a, b) where ``modes`` equals ``wanted``."""
    spans, start = [], None
    for i, m in enumerate([*modes, None]):
        if m == wanted and start is None:
            start = i
        elif m != wanted and start is not None:
            spans.append((start, i))
            start = None
    return spans


def plot_demo(path: Path, rtv3, direct, title: str, success_threshold: float, top_classes: int = 5) -> None:
    """Class weights (stacked, top classes), entropy bounds and goal distance over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.patches import Patch

    from rtv3_maniskill.features import DT

    diag = rtv3.diagnostics
    steps = len(diag)
    t = (np.arange(steps) + 1) * DT
    modes = [d["mode"] for d in diag]
    weights = np.stack([d["class_weights"] for d in diag]) if steps else np.zeros((0, 0))
    fig, axes = plt.subplots(3, 1, figsize=(9, 8.5), sharex=True, gridspec_kw=dict(height_ratios=[1.2, 1, 0.9]))
    for ax in axes:
        for mode, (color, alpha, _) in MODE_COLORS.items():
            for a, b in _spans(modes, mode):
                ax.axvspan(a * DT + DT / 2, b * DT + DT / 2, color=color, alpha=alpha, lw=0)

    ax = axes[0]
    if weights.size:
        k = weights.shape[1]
        order = np.argsort(-weights.max(0))
        top = order[: min(top_classes, k)]
        layers = [weights[:, c] for c in top]
        labels = [f"class {c}" for c in top]
        if k > len(top):
            layers.append(weights[:, order[len(top):]].sum(1))
            labels.append(f"other {k - len(top)}")
        ax.stackplot(t, *layers, labels=labels, alpha=0.85)
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    ax.set_ylim(0, 1)
    ax.set_ylabel("class weight p(z | ...)")
    ax.set_title(title, fontsize=10)

    ax = axes[1]
    if steps:
        for key, color, name in (("trans", "tab:blue", "translation"), ("rot", "tab:orange", "rotation")):
            ax.plot(t, [d[f"{key}_entropy_upper"] for d in diag], color=color, label=f"{name} upper bound")
            ax.plot(t, [d[f"{key}_entropy_lower"] for d in diag], color=color, ls="--", label=f"{name} lower bound")
    ax.set_ylabel("entropy (nats)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)

    ax = axes[2]
    for result, name, color in ((rtv3, "RT-V3", "tab:green"), (direct, "Direct", "tab:gray")):
        if result is None or not result.diagnostics:
            continue
        d = [x["pregrasp_distance"] for x in result.diagnostics]
        ax.plot((np.arange(len(d)) + 1) * DT, d, color=color,
                label=f"{name} ({result.outcome})")
    ax.axhline(success_threshold, color="k", lw=0.8, ls=":", label="success threshold")
    ax.set_ylabel("distance to pre-grasp")
    ax.set_xlabel("time (s)")
    handles, labels = ax.get_legend_handles_labels()
    handles += [Patch(color=c, alpha=max(a, 0.3)) for c, a, _ in MODE_COLORS.values()]
    labels += [text for *_, text in MODE_COLORS.values()]
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _pause_text(pauses: tuple[int, int] | None) -> str:
    return "" if pauses is None or pauses[1] == 0 else f" + pauses {pauses[0]}/{pauses[1]}"


def _outcome(result) -> str:
    from rtv3_maniskill.features import DT

    return (f"{result.outcome:9s}  reached={'yes' if result.success else 'no ':3s}  "
            f"contact={'yes' if result.collision else 'no ':3s}  "
            f"steps={result.steps:3d} ({result.steps * DT:4.2f} s simulated)  "
            f"final distance={result.final_distance:.3f}  "
            f"wall time={result.wall_time:5.1f} s")


def run(args: argparse.Namespace) -> int:
    import torch

    from rtv3_maniskill.benchmarks.episodes import controller_speed_limits, run_episode
    from rtv3_maniskill.policies.rtv3.checkpoints import load_policy
    from rtv3_maniskill.shared_control import SharedControlConfig
    from rtv3_maniskill.shared_control.methods import make_method
    from rtv3_maniskill.shared_control.simulated_users import make_user

    torch.set_num_threads(1)
    if args.max_steps < 1:
        raise SystemExit(f"error: --max-steps must be >= 1, got {args.max_steps}")
    try:
        make_user(args.user, pauses=args.pauses)
        fusion = SharedControlConfig.preset(fusion_name(args))
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    try:
        policy = load_policy(policy_path(args))
    except FileNotFoundError as err:
        raise SystemExit(f"error: {err}") from None
    args.output.mkdir(parents=True, exist_ok=True)

    env_kwargs = dict(num_points=int(policy.config.num_points), max_grasps=int(policy.config.max_grasps),
                      safety_filter=args.safety_filter, **scene_settings(args))
    env, can_render = _make_env(not args.no_video, env_kwargs)
    options = {} if args.target_grasp is None else dict(target_grasp_index=args.target_grasp)
    try:
        _, info = env.reset(seed=args.seed, options=options)
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    base = env.base
    target = int(info["target_grasp_index"][0])
    options = dict(target_grasp_index=target)
    objects = ", ".join(o.name for o in base.layouts[0].objects)
    count = int(base.grasps_mask[0].sum())
    print(f"scene {args.seed}: {len(base.layouts[0].objects)} objects ({objects}), {count} grasp candidates; "
          f"target grasp {target}; user '{args.user}' (seed {args.user_seed}){_pause_text(args.pauses)}; "
          f"up to {args.max_steps} steps")

    limits = controller_speed_limits(base)
    rtv3 = run_episode(env, make_method("rtv3", limits, policy=policy, config=fusion),
                       make_user(args.user, args.user_seed, pauses=args.pauses),
                       max_steps=args.max_steps, record_frames=can_render, seed=args.seed, options=options)
    goal_px = _goal_pixels(env) if can_render else None
    direct = run_episode(env, make_method("direct", limits), make_user(args.user, args.user_seed, pauses=args.pauses),
                         max_steps=args.max_steps, record_frames=can_render, seed=args.seed, options=options)
    threshold = float(base.success_threshold)
    env.close()

    video = args.output / "demo.mp4"
    if can_render and rtv3.frames:
        import imageio

        try:
            imageio.mimsave(video, _side_by_side(_annotate(direct.frames, direct.diagnostics, "Direct", goal_px),
                                                 _annotate(rtv3.frames, rtv3.diagnostics, "RT-V3", goal_px)),
                            fps=20, macro_block_size=1)
            print(f"video -> {video}")
        except Exception as err:  # noqa: BLE001  (no ffmpeg writer: keep the plot)
            print(f"note: video not written ({type(err).__name__}: {err})")
    plot = args.output / "demo.png"
    title = (f"RT-V3 shared control, scene {args.seed}, target grasp {target}, "
             f"user '{args.user}'{_pause_text(args.pauses)}")
    plot_demo(plot, rtv3, direct, title, threshold)
    print(f"plot  -> {plot}")

    counts = rtv3.mode_counts
    print("\noutcome (same scene, target and user noise):")
    print(f"  RT-V3  {_outcome(rtv3)}")
    print(f"  Direct {_outcome(direct)}")
    print(f"  RT-V3 modes: shared {counts.get('shared', 0)}, autonomous {counts.get('autonomous', 0)}, "
          f"user only {counts.get('user_only', 0)} steps")
    won = {name: r.outcome == "success" for name, r in (("rtv3", rtv3), ("direct", direct))}
    if won["rtv3"] and not won["direct"]:
        print("  -> with RT-V3 the user reached the pre-grasp without touching the scene; alone they did not.")
    elif won["rtv3"] and won["direct"]:
        delta = direct.steps - rtv3.steps
        print(f"  -> both reached it; RT-V3 took {abs(delta)} steps {'fewer' if delta >= 0 else 'more'}"
              f" ({abs(delta) * 0.05:.2f} s).")
    elif won["direct"]:
        print("  -> direct teleoperation reached it and RT-V3 did not in this run.")
    else:
        print("  -> neither reached the pre-grasp without a contact in this run.")
    print("  (outcome as in the benchmark: a contact fails a trial, even if the pre-grasp is reached afterwards)")
    return 0
