"""``pd_ee_twist``: end-effector body-twist control for the Panda, and the agent that offers it.

ManiSkill 3.0.1 has no twist controller (and ``pd_ee_delta_pose`` reads rotations as
XYZ Euler angles with a sign error, upstream issue #1469). This controller takes a body
twist ``[v (m/s), w (rad/s)]`` of the TCP frame, maps it to joint velocities with the
damped least-squares inverse of the TCP Jacobian, and drives the arm joints with both a
position target (the integrated virtual configuration) and a velocity target (feed
forward), so the realised twist follows the command in free space. Batched torch on
CPU and GPU (pytorch_kinematics Jacobians).
"""

from __future__ import annotations

import os
from contextlib import redirect_stderr, redirect_stdout
from copy import deepcopy
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pytorch_kinematics as pk
import torch
from gymnasium import spaces
from mani_skill.agents.controllers.pd_joint_pos import PDJointPosController, PDJointPosControllerConfig
from mani_skill.agents.registration import register_agent
from mani_skill.agents.robots.panda.panda import Panda

from rtv3_maniskill.robot.execution import EXECUTIONS
from rtv3_maniskill.robot.neo_qp import NeoConfig, NeoController, NeoSafetyFilter


@lru_cache(maxsize=4)
def _serial_chain(urdf_path: str, end_link: str, device: str) -> pk.SerialChain:
    with open(urdf_path, "rb") as f:
        urdf = f.read()
    with open(os.devnull, "w") as null, redirect_stdout(null), redirect_stderr(null):
        chain = pk.build_serial_chain_from_urdf(urdf, end_link_name=end_link)
    return chain.to(device=device)


def clamp_twist_norms(twist: torch.Tensor, max_linear: float, max_angular: float) -> torch.Tensor:
    """Scale ``(..., 6)`` twists down so that ``|v| <= max_linear`` and ``|w| <= max_angular``."""
    v, w = twist[..., :3], twist[..., 3:]
    v = v * (max_linear / v.norm(dim=-1, keepdim=True).clamp_min(max_linear))
    w = w * (max_angular / w.norm(dim=-1, keepdim=True).clamp_min(max_angular))
    return torch.cat([v, w], -1)


class PDEETwistController(PDJointPosController):
    """Arm controller whose action is the TCP body twist ``(B, 6)`` ``[v, w]``."""

    config: PDEETwistControllerConfig

    def _initialize_joints(self):
        super()._initialize_joints()
        self.chain = _serial_chain(self.config.urdf_path, self.config.ee_link, str(self.device))
        limits = self.articulation.get_qlimits()[0, self.active_joint_indices]
        self._q_low, self._q_high = limits[:, 0].to(self.device), limits[:, 1].to(self.device)

    def _initialize_action_space(self):
        high = np.array([self.config.max_linear_speed] * 3 + [self.config.max_angular_speed] * 3, dtype=np.float32)
        self.single_action_space = spaces.Box(-high, high, dtype=np.float32)

    def joint_velocities(self, q: torch.Tensor, body_twist: torch.Tensor) -> torch.Tensor:
        """``q (B, 7)``, TCP body twist ``(B, 6)`` -> joint velocities ``(B, 7)`` (damped least squares)."""
        # (B, 6, 7): [v; w] of the TCP origin in robot-base axes, and the TCP pose.
        jac, tcp = self.chain.jacobian(q, ret_eef_pose=True)
        rot = tcp[:, :3, :3]
        twist_base = torch.cat([rot @ body_twist[:, :3, None], rot @ body_twist[:, 3:, None]], 1)
        damping = self.config.ik_damping**2 * torch.eye(6, device=q.device, dtype=q.dtype)
        qd = jac.transpose(1, 2) @ torch.linalg.solve(jac @ jac.transpose(1, 2) + damping, twist_base)
        qd = qd[..., 0]
        # Keep every joint within its speed limit by scaling the whole vector (keeps direction).
        scale = (self.config.max_joint_speed / qd.abs().amax(-1, keepdim=True).clamp_min(1e-9)).clamp(max=1.0)
        return qd * scale

    def set_action(self, action):
        action = self._preprocess_action(action)
        action = self.config.command_gain * clamp_twist_norms(action, self.config.max_linear_speed,
                                                              self.config.max_angular_speed)
        self._step = 0
        self._start_qpos = self.qpos
        # Integrate the virtual (target) configuration; re-anchor it to the measured one when
        # they drift apart (contact), so the arm does not wind up against an obstacle.
        drift = (self._target_qpos - self.qpos).abs().amax(-1, keepdim=True)
        reference = torch.where(drift > self.config.max_target_drift, self.qpos, self._target_qpos)
        qd = self.joint_velocities(reference, action.to(reference.dtype))
        dt = 1.0 / self._control_freq
        self._target_qpos = torch.clamp(reference + qd * dt, self._q_low, self._q_high)
        self.set_drive_targets(self._target_qpos)
        self.articulation.set_joint_drive_velocity_targets(qd, self.joints, self.active_joint_indices)


@dataclass
class PDEETwistControllerConfig(PDJointPosControllerConfig):
    ee_link: str = "panda_hand_tcp"
    urdf_path: str = ""
    max_linear_speed: float = 0.3
    """m/s; commands with a larger translation speed are scaled down."""
    max_angular_speed: float = 1.2
    """rad/s; commands with a larger rotation speed are scaled down."""
    command_gain: float = 1.0
    """Share of the (clamped) commanded twist the arm executes in a step: 1 follows the command, 0.75
    is what the RT-V3 authors' pose-target tracking (QP gain 15 at 20 Hz) executes."""
    max_joint_speed: float = 2.0
    """rad/s per joint (the Panda allows 2.175-2.61)."""
    ik_damping: float = 0.02
    max_target_drift: float = 0.1
    """rad; beyond this the virtual configuration is re-anchored to the measured one."""
    normalize_action: bool = False
    controller_cls = PDEETwistController


class PDEETwistQPController(PDEETwistController):
    """``pd_ee_twist_qp``: the TCP body twist ``(B, 6)`` tracked by the NEO QP (``robot/neo_qp.py``).

    Joint position and velocity limits hold (velocity dampers near the limits); obstacles are not
    avoided unless a ``NeoSafetyFilter`` is attached per sub-scene (``attach_safety_filters``), whose
    collision damper then decides the joint velocities. Position and velocity drive targets as in
    ``pd_ee_twist``.
    """

    config: PDEETwistQPControllerConfig

    def _initialize_joints(self):
        super()._initialize_joints()
        neo = NeoConfig(dt=1.0 / self._control_freq, collision_damper=False)
        controller = NeoController(None, neo)
        self.qp_controllers: list[NeoController] = [controller] + [
            NeoController(None, neo, kinematics=controller.kin) for _ in range(self.articulation.pose.p.shape[0] - 1)
        ]
        self.safety_filters: list[NeoSafetyFilter | None] = [None] * len(self.qp_controllers)

    def attach_safety_filters(self, filters: list[NeoSafetyFilter | None]) -> None:
        """One filter (or None: limits only) per sub-scene; the filters' ``reset`` sets their scenes."""
        if len(filters) != len(self.qp_controllers):
            raise ValueError(f"need one safety filter per sub-scene ({len(self.qp_controllers)}), got {len(filters)}")
        self.safety_filters = list(filters)

    def joint_velocities(self, q: torch.Tensor, body_twist: torch.Tensor) -> torch.Tensor:
        """``q (B, 7)``, TCP body twist ``(B, 6)`` -> joint velocities ``(B, 7)`` (one QP per sub-scene)."""
        if q.shape[0] != len(self.qp_controllers):
            raise ValueError(f"expected {len(self.qp_controllers)} configurations, got q of shape {tuple(q.shape)}")
        q_np = q.detach().cpu().double().numpy()
        twist_np = body_twist.detach().cpu().double().numpy()
        out = []
        for i, (ctrl, filt) in enumerate(zip(self.qp_controllers, self.safety_filters)):
            step = filt.filter(q_np[i], twist_np[i]) if filt is not None else ctrl.step(q_np[i], twist_np[i])
            out.append(step.joint_velocities)
        return torch.as_tensor(np.stack(out), dtype=q.dtype, device=q.device)


@dataclass
class PDEETwistQPControllerConfig(PDEETwistControllerConfig):
    controller_cls = PDEETwistQPController


def set_execution(agent, execution: str) -> None:
    """Set the twist execution (:data:`EXECUTIONS`) of every twist controller ``agent`` has built."""
    if execution not in EXECUTIONS:
        raise ValueError(f"unknown execution {execution!r}; expected one of {tuple(EXECUTIONS)}")
    for combined in agent.controllers.values():
        arm = getattr(combined, "controllers", {}).get("arm")
        if isinstance(arm, PDEETwistController):
            for key, value in EXECUTIONS[execution].items():
                setattr(arm.config, key, value)
            arm._initialize_action_space()


def attach_safety_filters(env, filters: list[NeoSafetyFilter | None]) -> None:
    """Put one ``NeoSafetyFilter`` per sub-scene into a ``pd_ee_twist_qp`` env (unwrapped or wrapped)."""
    arm = env.unwrapped.agent.controller.controllers.get("arm")
    if not isinstance(arm, PDEETwistQPController):
        mode = env.unwrapped.control_mode
        raise ValueError(f"safety filters need control_mode='pd_ee_twist_qp', the env uses {mode!r}")
    arm.attach_safety_filters(filters)


def target_object_index(env, index: int = 0) -> int:
    """Index (into ``env.layouts[index].objects``) of the object that sub-scene ``index``'s target grasp holds."""
    base = env.unwrapped
    grasp = int(base.target_grasp_index[index])
    return int(base.grasp_sets[index].object_ids[grasp])


@register_agent()
class PandaTwist(Panda):
    """ManiSkill's Panda plus the ``pd_ee_twist`` and ``pd_ee_twist_qp`` control modes (all Panda modes still work)."""

    uid = "panda_twist"

    @property
    def _controller_configs(self):
        configs = super()._controller_configs
        arm = PDEETwistControllerConfig(
            self.arm_joint_names,
            lower=None,
            upper=None,
            stiffness=self.arm_stiffness,
            damping=self.arm_damping,
            force_limit=self.arm_force_limit,
            ee_link=self.ee_link_name,
            urdf_path=self.urdf_path,
        )
        configs["pd_ee_twist"] = dict(arm=arm, gripper=deepcopy(configs["pd_joint_pos"]["gripper"]))
        arm_qp = PDEETwistQPControllerConfig(**{k: getattr(arm, k) for k in arm.__dataclass_fields__})
        configs["pd_ee_twist_qp"] = dict(arm=arm_qp, gripper=deepcopy(configs["pd_joint_pos"]["gripper"]))
        return configs


__all__ = [
    "PDEETwistController",
    "PDEETwistControllerConfig",
    "PDEETwistQPController",
    "PDEETwistQPControllerConfig",
    "PandaTwist",
    "attach_safety_filters",
    "clamp_twist_norms",
    "set_execution",
    "target_object_index",
]
