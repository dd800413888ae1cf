"""Which grasp candidates can be a trial's goal (docs/PAPER_DETAILS.md, "Authors' benchmark protocol").

The authors sample feasible grasps only. A candidate is a *feasible goal* when the arm can stand
at its pre-grasp without touching anything (a collision-free IK solution) and can then move
straight in to the grasp along the tool z, 5 cm, without touching anything but the target object.
Both are checked for the twin a user aims at: of the grasp and the same grasp turned by pi about
its approach axis, the one nearer the start orientation (the ready pose). Candidates that fail are
counted by reason and never run as trials.
"""

from __future__ import annotations

import numpy as np
import torch

from rtv3_maniskill.features import pregrasp_poses
from rtv3_maniskill.robot.planner import PandaPlanner
from rtv3_maniskill.robot.scene_geometry import READY_QPOS
from rtv3_maniskill.tasks.grasp_sampler import canonicalize_symmetric

GOAL_CHECKS = ("feasible", "no_ik_pregrasp", "blocked_approach")
"""Outcomes of :func:`check_goal`: feasible, no collision-free IK at the pre-grasp, or the straight
5 cm approach from there to the grasp collides or leaves the arm's reach."""


def aimed_grasp(grasp_pose: np.ndarray, reference_tcp: np.ndarray) -> np.ndarray:
    """``(4, 4)`` the twin of ``grasp_pose`` nearer the orientation of ``reference_tcp (4, 4)``."""
    return canonicalize_symmetric(np.asarray(grasp_pose)[None], np.asarray(reference_tcp))[0]


def aimed_pregrasp(planner, grasp_pose) -> np.ndarray:
    """``(4, 4)`` the pre-grasp of the twin of ``grasp_pose`` (world) a user aims at from the ready pose."""
    reference = planner.forward_kinematics(READY_QPOS)
    grasp = aimed_grasp(np.asarray(grasp_pose.detach().cpu() if hasattr(grasp_pose, "detach") else grasp_pose,
                                   dtype=np.float64), reference)
    return pregrasp_poses(torch.from_numpy(grasp)).numpy()


def check_goal(planner, grasp_pose: np.ndarray, target_object: int, reference_tcp: np.ndarray,
               seed: int = 0) -> str:
    """One of :data:`GOAL_CHECKS` for the grasp ``grasp_pose (4, 4)`` (world) of ``target_object``.

    Args:
        planner: a :class:`~rtv3_maniskill.robot.planner.PandaPlanner` of the scene.
        reference_tcp: ``(4, 4)`` the TCP pose trials start from (picks the twin aimed at).
        seed: seeds the IK restarts.
    """
    grasp = aimed_grasp(grasp_pose, reference_tcp)
    pregrasp = pregrasp_poses(torch.from_numpy(grasp)).numpy()
    q_pre = planner.solve_ik(pregrasp, READY_QPOS, seed=seed)
    if q_pre is None:
        return "no_ik_pregrasp"
    approach = planner.plan_straight_line(q_pre, grasp, ignore_objects={int(target_object)})
    return "feasible" if approach.success else "blocked_approach"


def check_scene_goals(env_base, planner=None, seed: int = 0) -> list[str]:
    """:func:`check_goal` for every candidate of the loaded scene of ``env_base`` (a single
    ``GraspClutter-v1`` env, unwrapped), in candidate order; padding rows are left out."""
    if planner is None:
        planner = PandaPlanner(env_base.layouts[0])
    return [check_candidate(env_base, planner, i, seed) for i in range(len(env_base.grasp_sets[0].scores))]


def check_candidate(env_base, planner, index: int, seed: int = 0) -> str:
    """:func:`check_goal` for candidate ``index`` of the loaded scene of ``env_base``, from the ready pose,
    its IK restarts seeded by ``seed`` (the scene's seed) and ``index``."""
    grasp_set = env_base.grasp_sets[0]
    return check_goal(planner, np.asarray(grasp_set.poses[index]), int(grasp_set.object_ids[index]),
                      planner.forward_kinematics(READY_QPOS), seed=seed * 1009 + index)
