"""Model card of saved RT-V3 policies: the template (Jinja, rendered by ``huggingface_hub.ModelCard``)
and the training dataset it names."""

from __future__ import annotations

import json
from pathlib import Path


def training_dataset_repo_id(dataset_meta=None, pretrained_dir: str | Path | None = None) -> str | None:
    """Repo id of the dataset a policy was trained on, for the card's ``datasets:`` field.

    From LeRobot's dataset metadata (``lerobot-train`` hands it to the policy as
    ``dataset_meta``), else from a local checkpoint folder: its ``train_config.json``
    (``dataset.repo_id``, written by ``lerobot-train``) or the ``datasets:`` of its model card.
    ``None`` when unknown (the card then names no dataset rather than a wrong one).
    """
    repo_id = getattr(dataset_meta, "repo_id", None)
    if repo_id:
        return str(repo_id)
    if pretrained_dir is None or not Path(pretrained_dir).is_dir():
        return None
    folder = Path(pretrained_dir)
    train_config = folder / "train_config.json"
    if train_config.is_file():
        try:
            repo_id = (json.loads(train_config.read_text()).get("dataset") or {}).get("repo_id")
        except (json.JSONDecodeError, AttributeError):
            repo_id = None
        if repo_id:
            return str(repo_id)
    readme = folder / "README.md"
    if readme.is_file():
        from huggingface_hub import ModelCard

        datasets = ModelCard.load(readme).data.datasets
        if isinstance(datasets, str):
            return datasets
        if datasets:
            return str(datasets[0])
    return None


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
