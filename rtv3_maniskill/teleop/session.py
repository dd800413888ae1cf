"""An interactive shared-control session: a person (or a simulated user) grasps objects in clutter.

Per trial: ``GraspClutter-v1`` loads scene ``scene_seed + trial`` and its target grasp; at 20 Hz the
input source gives a command, the grasp buttons (:mod:`grasp_actions`) may run a scripted motion,
otherwise the assistance method (``make_method``: direct, HO or RT-V3) turns the command into the
robot's twist; while the gripper is closed the user drives alone. :mod:`grasp_trial` decides the
outcome (success, timeout, collision, unmatched); the trial is recorded as one LeRobot episode.
"""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rtv3_maniskill import features, se3
from rtv3_maniskill.benchmarks.episodes import SharedControlEnv, controller_speed_limits, render_frame
from rtv3_maniskill.datagen.demonstrations import describe_grasp, state_vector
from rtv3_maniskill.features import GRIPPER_CLOSED
from rtv3_maniskill.shared_control.config import SharedControlConfig
from rtv3_maniskill.shared_control.copilot import CopilotSettings
from rtv3_maniskill.shared_control.methods import make_method, method_spec
from rtv3_maniskill.teleop.display import TeleopDisplay
from rtv3_maniskill.teleop.grasp_actions import EVENTS, GraspActionConfig, GraspActions
from rtv3_maniskill.teleop.grasp_trial import GraspTrialMonitor, TrialConfig
from rtv3_maniskill.teleop.inputs import SimulatedOperator, make_input
from rtv3_maniskill.teleop.recorder import SessionRecorder
from rtv3_maniskill.teleop.render import RenderProcess, scene_state


@dataclass
class SessionConfig:
    """What ``rtv3 teleop`` runs (see ``rtv3 teleop --help``)."""

    method: str = "rtv3"
    input: str = "keyboard"
    scene_seed: int = 0
    trials: int = 1
    participant: str = "P0"
    record: Path | None = None
    resume: bool = False
    """Continue the session recorded in ``record`` (same settings) with its next trial."""
    headless: bool = False
    realtime: bool | None = None
    """Pace steps at 20 Hz (default: for a person, not for a simulated user)."""
    policy_path: Path | None = None
    scene_type: str = "pile"
    object_source: str = "procedural"
    execution: str = "capped"
    """How the env executes the assisted twist (``rtv3_maniskill.presets.EXECUTIONS``)."""
    self_contacts: bool = True
    fusion: str = "tuned"
    """RT-V3's fusion preset (``SharedControlConfig.preset``; ``rtv3 teleop`` takes the scene preset's)."""
    target_grasp: int | None = None
    init_qpos: np.ndarray | None = None
    """Start joint positions (7,) instead of the rest pose (e.g. IK of the pre-grasp)."""
    user_seed: int = 0
    copilot: CopilotSettings | None = None
    """Which diffusion copilot ``method="copilot"`` runs, with which gamma (None: the shipped one, its default)."""
    safety_filter: str | None = None
    """``"neoss"``: the NEO collision damper between the method's twist and the arm (``SharedControlEnv``)."""
    screenshot: Path | None = None
    screenshot_step: int | None = None
    trial_config: TrialConfig = field(default_factory=TrialConfig)
    grasp_config: GraspActionConfig = field(default_factory=GraspActionConfig)


@dataclass
class TrialResult:
    """One finished trial."""

    trial: int
    scene_seed: int
    outcome: str
    steps: int
    contacts: int
    task: str
    episode_index: int | None = None


def _class_weights(diagnostics: dict) -> np.ndarray | None:
    weights = diagnostics.get("class_weights", diagnostics.get("belief"))
    return None if weights is None else np.asarray(weights, dtype=np.float32)


def _rate(times: deque) -> float:
    """Events per second over the times in ``times`` (0 with fewer than two)."""
    return (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 and times[-1] > times[0] else 0.0


class _SceneOverlay:
    """Pixels of the target object and the grasp candidates in the window's camera, for one trial."""

    def __init__(self, base: Any) -> None:
        camera = base.scene.human_render_cameras["render_camera"]
        params = camera.get_params()
        self.extrinsic = params["extrinsic_cv"][0].double().cpu().numpy()  # (3, 4) world -> camera
        self.intrinsic = params["intrinsic_cv"][0].double().cpu().numpy()  # (3, 3)
        self.base = base
        target = int(base.grasp_sets[0].object_ids[int(base.target_grasp_index[0])])
        self.target_actor = base.objects[0][target]
        self.target_centre = base.layouts[0].objects[target].collision_mesh().centroid  # object frame
        grasps = base.grasp_poses[0].double().cpu()
        ends = torch.stack([features.pregrasp_poses(grasps)[:, :3, 3], grasps[:, :3, 3]], 1)  # (M, 2, 3)
        self.grasp_pixels = self.project(ends.reshape(-1, 3).numpy()).reshape(-1, 4)

    def project(self, points: np.ndarray) -> np.ndarray:
        """``(K, 3)`` world points -> ``(K, 2)`` pixel coordinates (u right, v down)."""
        cam = points @ self.extrinsic[:, :3].T + self.extrinsic[:, 3]
        pix = cam @ self.intrinsic.T
        return pix[:, :2] / np.maximum(pix[:, 2:3], 1e-6)

    def draw(self, diagnostics: dict[str, Any]) -> dict[str, Any]:
        """The display's ``overlay``: the target object now, and the candidates the prior aims at."""
        pose = self.target_actor.pose
        rotation = se3.quat_to_matrix(pose.q[0].double().cpu()).numpy()
        centre = rotation @ self.target_centre + pose.p[0].double().cpu().numpy()
        grasps = []
        belief = diagnostics.get("grasp_belief")
        for i in diagnostics.get("shown_grasps", ()):
            weight = 1.0 if belief is None else float(belief[int(i)])
            grasps.append((*self.grasp_pixels[int(i)], weight))
        return dict(target=self.project(centre[None])[0], grasps=grasps)


class TeleopSession:
    """Builds the env, method, input, window and recorder of a :class:`SessionConfig`; :meth:`run` plays it."""

    def __init__(self, config: SessionConfig) -> None:
        self.config = config
        fusion = SharedControlConfig.preset(config.fusion)  # an unknown name fails before anything starts
        policy = None
        num_points, max_grasps = features.DEFAULT_NUM_POINTS, features.DEFAULT_MAX_GRASPS
        if method_spec(config.method).needs_policy:
            # Lazy: the policy package loads LeRobot's config (~1.5 s), which a session without the prior skips.
            from rtv3_maniskill.policies.rtv3.checkpoints import load_policy

            policy = load_policy(config.policy_path)
            num_points, max_grasps = int(policy.config.num_points), int(policy.config.max_grasps)
        # a 320 px view (the window scales it to 512): rendering is the slowest part on a CPU
        render = dict(render_mode="rgb_array", human_render_camera_configs=dict(width=320, height=320))
        render = render if not config.headless else {}
        scene = dict(num_points=num_points, max_grasps=max_grasps, scene_type=config.scene_type,
                     object_source=config.object_source, execution=config.execution, self_contacts=config.self_contacts)
        # Paced for a person, the window's frames are rendered in a process of their own (teleop_render).
        self.renderer = None
        if not config.headless and self._realtime:
            camera = render["human_render_camera_configs"]
            self.renderer = RenderProcess({**scene, "human_render_camera_configs": camera})
        self.env = SharedControlEnv(rendered_context=True, safety_filter=config.safety_filter, **scene, **render)
        self.env.method = make_method(config.method, controller_speed_limits(self.env.base), policy=policy,
                                      config=fusion, copilot=config.copilot)
        self.speed_limits = controller_speed_limits(self.env.base)
        self.display = None
        if not config.headless:  # the window opens once the scene can be shown
            self.display = TeleopDisplay()
        self.input = make_input(config.input, config.user_seed)
        self.simulated = isinstance(self.input, SimulatedOperator)
        self.actions = GraspActions(config.grasp_config)
        self.monitor = GraspTrialMonitor(self.env.base, config.trial_config)
        self.recorder = None
        if config.record is not None:
            self.recorder = SessionRecorder(config.record, num_points, max_grasps, resume=config.resume, settings=dict(
                method=self.method_label, input=config.input, participant=config.participant,
                scene_seed=config.scene_seed, trials=config.trials, timeout_s=config.trial_config.timeout_s,
                scene_type=config.scene_type,
                **({"object_source": config.object_source} if config.object_source != "procedural" else {}),
                **({"fusion": config.fusion} if config.fusion != "tuned" else {}),
                **({"copilot": dataclasses.asdict(config.copilot)} if config.copilot else {})))
        self.quit = False
        self.interrupted = False
        """Ctrl-C came: the trial in progress ends as ``aborted`` (recorded as Esc would) and the session ends."""
        self.rates: dict[str, float] = {}
        """Achieved control and display rates (Hz) of the last trial: steps and frames over its wall time."""
        self._shots = 0

    def run(self) -> list[TrialResult]:
        """Play ``config.trials`` trials (Esc or closing the window aborts); returns their results."""
        results = []
        first = 0 if self.recorder is None else self.recorder.trials  # a resumed session goes on from there
        # Ctrl-C is a request to stop, read between control steps, not an exception thrown into the middle of
        # a write: the session ends at the next step with everything recorded so far intact.
        main_thread = threading.current_thread() is threading.main_thread()  # signal handlers live there only
        previous = signal.signal(signal.SIGINT, self._interrupt) if main_thread else None
        try:
            for trial in range(first, self.config.trials):
                results.append(self.run_trial(trial))
                if self.quit or self.interrupted:
                    break
        finally:
            if main_thread:
                signal.signal(signal.SIGINT, previous)
            self.close()
        return results

    def _interrupt(self, signum: int, frame: Any) -> None:
        self.interrupted = True

    @property
    def method_label(self) -> str:
        """The method as ``sessions.csv`` and the study name it: ``rtv3``, or ``rtv3+neoss`` behind the damper
        (as ``benchmark-shared`` labels its rows)."""
        return self.config.method + (f"+{self.config.safety_filter}" if self.config.safety_filter else "")

    @property
    def _realtime(self) -> bool:
        """Paced at 20 Hz: ``config.realtime``, by default for a person and not for a simulated user."""
        if self.config.realtime is not None:
            return self.config.realtime
        return not self.config.input.strip().lower().startswith("simulated:")

    def close(self) -> None:
        """Finalize the recording and close the window and env."""
        if self.recorder is not None:
            self.recorder.close()
        if self.renderer is not None:
            self.renderer.close()
        if self.display is not None:
            self.display.close()
        self.env.close()

    def _reset(self, scene_seed: int) -> dict:
        options: dict[str, Any] = {}
        if self.config.target_grasp is not None:
            options["target_grasp_index"] = self.config.target_grasp
        obs, _ = self.env.reset(seed=scene_seed, options=options)
        if self.config.init_qpos is not None:
            options.update(init_qpos=np.asarray(self.config.init_qpos),
                           target_grasp_index=int(self.env.base.target_grasp_index[0]))
            obs, _ = self.env.reset(seed=scene_seed, options=options)
        return obs

    def run_trial(self, trial: int) -> TrialResult:
        """One trial on scene ``scene_seed + trial``."""
        cfg, env = self.config, self.env
        scene_seed = cfg.scene_seed + trial
        obs = self._reset(scene_seed)
        base = env.base
        target_index = int(base.target_grasp_index[0])
        self.actions.reset()
        env.gripper = self.actions.gripper
        self.monitor.reset()
        if self.simulated:
            self.input.reset(env, self.actions)
        else:
            self.input.reset(env)
        names = [o.name for o in base.layouts[0].objects]
        task = describe_grasp(names[self.monitor.target_object], base.target_grasp_pose[0].double().cpu().numpy())
        extra = obs["extra"]
        if self.recorder is not None:
            keys = ("point_cloud", "point_cloud_mask", "grasps", "grasps_mask")
            context = {k: extra[k][0].cpu().numpy() for k in keys}
            self.recorder.start_trial(context, task, participant=cfg.participant, method=self.method_label,
                                      input=cfg.input, scene_seed=scene_seed, target_grasp_index=target_index,
                                      target_object=self.monitor.target_object)
        realtime = self._realtime
        panel = dict(method=self.method_label, input=cfg.input, trial=f"{trial + 1}/{cfg.trials}", task=task,
                     timeout=cfg.trial_config.timeout_s, mode="none", phase="free", gripper="open")
        overlay = _SceneOverlay(base) if self.display is not None else None
        if self.display is not None:  # "starting" until the window shows the trial's first frame
            self.display.draw(render_frame(env), dict(panel, mode="starting", time=0.0, contacts=0), overlay.draw({}))
        # Warm up before the clock starts: the first assisted step and the first frame cost the most.
        env.method.step(features.observation_from_env(obs), None)
        env.method.reset()
        if self.renderer is not None:  # (only with a window) the clock starts once it shows this scene
            self.renderer.set_scene(scene_seed, idle=self.display.events)
            first = self.renderer.first_frame(*scene_state(base), idle=self.display.events)
            self.display.draw(first, dict(panel, time=0.0, contacts=0), overlay.draw({}))
        elif self.display is not None:
            self.display.draw(None, dict(panel, time=0.0, contacts=0), overlay.draw({}))
        if self.display is not None:
            self.display.events()  # keys pressed while the scene loaded do not count
        print(f"trial {trial + 1}: scene {scene_seed}, {task}: started", flush=True)
        outcome, info, step = None, {}, 0
        steps_at, frames_at = deque(maxlen=20), deque(maxlen=20)  # times of the last steps and frames
        next_tick = clock_start = time.perf_counter()
        frames = 0
        while outcome is None:
            events = self.display.events() if self.display is not None else []
            if self._handle_window_events(events) or self.interrupted:
                outcome = "aborted"
                break
            tcp = base.tcp_pose_matrix[0].detach().cpu().double()
            user = self.input.poll(tcp, events)
            for button in user.buttons:
                self.actions.press(button)
            pressed = np.array([int(e in user.buttons) for e in EVENTS], dtype=np.int64)
            scripted = self.actions.step(tcp)
            env.gripper = self.actions.gripper
            state = state_vector(obs)
            if scripted is not None:
                obs, _, _, _, info = env.step_scripted(scripted, "scripted", user_twist=user.body)
            elif self.actions.gripper == GRIPPER_CLOSED:  # holding: the user alone drives
                obs, _, _, _, info = env.step_scripted(self._clamp(user.body), "user_only", user_twist=user.body)
            else:
                obs, _, _, _, info = env.step(user.body.numpy())
            step += 1
            diagnostics = info["assistance"]
            closed = self.actions.gripper == GRIPPER_CLOSED
            outcome = self.monitor.update(info, closed)
            if self.recorder is not None:
                self.recorder.add_step(state, user.raw.numpy(), info["robot_twist"].numpy(), info["assistance_mode"],
                                       _class_weights(diagnostics), pressed, self.actions.gripper,
                                       bool(info["success"][0]))
            steps_at.append(time.perf_counter())
            next_tick += features.DT
            shot = cfg.screenshot is not None and cfg.screenshot_step == step
            # Paced (a person at the controls), frames come from the render process whenever one is done;
            # unpaced (a simulated user), every step is rendered here, as is a screenshot's or the last step.
            frame = None
            if self.display is not None:
                if self.renderer is not None and not shot and outcome is None:
                    self.renderer.show(*scene_state(base))
                    frame = self.renderer.frame()
                else:
                    frame = render_frame(env)
            if frame is not None:
                frames_at.append(time.perf_counter())
                frames += 1
                panel.update(mode=info["assistance_mode"] or "none", phase=self.actions.phase,
                             gripper="closed" if closed else "open", control_hz=_rate(steps_at),
                             display_hz=_rate(frames_at))
                self.display.draw(frame, dict(panel, time=step * features.DT, contacts=self.monitor.contacts,
                                              diagnostics=diagnostics, outcome=outcome), overlay.draw(diagnostics))
                if shot:
                    self.display.screenshot(cfg.screenshot)
            if realtime:
                time.sleep(max(0.0, next_tick - time.perf_counter()))
            else:
                next_tick = time.perf_counter()
        wall = max(time.perf_counter() - clock_start, 1e-9)
        self.rates = dict(control_hz=step / wall, display_hz=frames / wall)
        episode = None
        if self.recorder is not None and step > 0:
            episode = self.recorder.end_trial(outcome, state_vector(obs), step * features.DT, self.monitor.contacts)
        print(f"trial {trial + 1}: scene {scene_seed}, {task}: {outcome} after {step * features.DT:.1f} s "
              f"({self.monitor.contacts} contact steps; control {self.rates['control_hz']:.1f} Hz, display "
              f"{self.rates['display_hz']:.1f} Hz)", flush=True)
        return TrialResult(trial, scene_seed, outcome, step, self.monitor.contacts, task, episode)

    def _clamp(self, twist: torch.Tensor) -> torch.Tensor:
        lin, ang = self.speed_limits
        v, w = twist[:3], twist[3:]
        v = v * min(1.0, lin / max(float(v.norm()), 1e-12))
        w = w * min(1.0, ang / max(float(w.norm()), 1e-12))
        return torch.cat([v, w])

    def _handle_window_events(self, events: list) -> bool:
        """Esc / window close -> quit (True); F12 -> screenshot."""
        if self.display is None:
            return False
        pg = self.display.pygame
        for event in events:
            if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key == pg.K_ESCAPE):
                self.quit = True
                return True
            if event.type == pg.KEYDOWN and event.key == pg.K_F12:
                folder = self.config.record if self.config.record is not None else Path(".")
                path = self.config.screenshot or folder / f"screenshot_{self._shots}.png"
                self._shots += 1
                print(f"screenshot: {self.display.screenshot(path)}", flush=True)
        return False


__all__ = ["SessionConfig", "TeleopSession", "TrialResult"]
