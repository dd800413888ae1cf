"""Model-card template for saved RT-V3 policies (Jinja, rendered by ``huggingface_hub.ModelCard``)."""

MODEL_CARD_TEMPLATE = """---
{{ card_data }}
---

# RT-V3 prior (LeRobot policy type `rtv3`)

Robot Trajectron V3 prior for probabilistic shared control of SE(3) grasping: a conditional
VAE with a discrete maneuver class that predicts the distribution of the next {{ horizon }}
end-effector body twists from the last {{ history }} end-effector states, a point cloud of the
scene ({{ num_points }} points) and up to {{ max_grasps }} grasp candidates. All inputs are
expressed in the current end-effector frame, which makes the prediction SE(3)-equivariant.

- Maneuver classes K: {{ classes }}
- Grasp encoder: {{ grasp_encoder }}; point-cloud encoder: {{ point_encoder }}
- Translation-conditioned rotation (factorized): {{ factorized }}
- Parameters: {{ num_parameters }}; training steps: {{ train_steps }}

## Inputs and outputs

`observation.state` (T, 27), `observation.point_cloud` (N, 6), `observation.point_cloud_mask` (N,),
`observation.grasps` (M, 9), `observation.grasps_mask` (M,) -- or the packed
`observation.environment_state` -- see `rtv3_maniskill/features.py`. Output: `action` (6,), body
twist [v (m/s), w (rad/s)]; `predict_step0_mixture` gives the step-0 Gaussian mixture used by the
shared-control posterior.

## Use

```python
from rtv3_maniskill.policies.rtv3.modeling_rtv3 import RTV3Policy
policy = RTV3Policy.from_pretrained("<this folder>")
twist = policy.select_action(observation)
```

Train with `lerobot-train --policy.type=rtv3 --policy.push_to_hub=false ...` once the
`lerobot_policy_rtv3` plugin distribution is installed.

- **License:** {{ license | default("[More Information Needed]", true) }}
"""
