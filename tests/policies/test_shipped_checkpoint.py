"""The shipped RT-V3 checkpoint: loads, and its prediction depends on where the user goes.

A prior that ignores its grasp context can only extrapolate the current motion; the posterior
then has nothing to add to a user's command (this caught a collapsed grasp encoder).
"""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch

import rtv3_maniskill  # noqa: F401  (registers GraspClutter-v1)
from rtv3_maniskill import features, se3
from rtv3_maniskill.features import PREGRASP_DISTANCE, context_mask
from rtv3_maniskill.policies.rtv3 import load_policy

pytestmark = pytest.mark.sim  # every test here runs the simulator


@pytest.fixture(scope="module")
def policy():
    return load_policy()


def test_shipped_checkpoint_heads_for_the_goal_it_is_given(policy):
    """From rest in a clutter scene, with one candidate grasp as context, the heading of the
    predicted 12-step motion (most likely class) changes with the candidate and, on average over
    the scene's candidates, points towards the candidate's pre-grasp (mean cosine > 0.5)."""
    env = gym.make("GraspClutter-v1", obs_mode="state_dict", control_mode="pd_ee_twist",
                   num_points=policy.config.num_points, max_grasps=policy.config.max_grasps)
    try:
        obs, _ = env.reset(seed=900000)
        base = env.unwrapped
        observation = features.observation_from_env(obs)
        cloud, cloud_mask = base.capture_point_cloud()  # the depth-camera cloud the data was made with
        observation[features.POINT_CLOUD], observation[features.POINT_CLOUD_MASK] = cloud.float(), cloud_mask.float()
        valid = torch.nonzero(base.grasps_mask[0] > 0.5).flatten().tolist()
        assert len(valid) >= 4
        tcp = base.tcp_pose_matrix[0].double()
        displacements, towards = [], []
        for g in valid[:: max(1, len(valid) // 8)]:
            policy.reset()
            ctx = dict(observation,
                       **{features.GRASPS_MASK: context_mask(observation[features.GRASPS_MASK], g, "target")})
            chunk = policy.predict_action_chunk(ctx)[0].double()  # (H, 6) body twists
            end = se3.integrate_body_twists(tcp, chunk, features.DT)[-1]
            moved = end[:3, 3] - tcp[:3, 3]
            pregrasp = se3.translate_along_z(base.grasp_poses[0, g].double(), -PREGRASP_DISTANCE)[:3, 3]
            displacements.append(moved)
            towards.append(float(torch.nn.functional.cosine_similarity(moved, pregrasp - tcp[:3, 3], 0)))
    finally:
        env.close()
    directions = torch.nn.functional.normalize(torch.stack(displacements), dim=-1)
    spread = directions.std(0).norm()  # 0 when every goal gives the same heading
    assert spread > 0.05, f"the predicted heading barely depends on the goal (spread {float(spread):.3f})"
    assert sum(towards) / len(towards) > 0.5, f"the predicted motion does not head for the goal: cosines {towards}"
