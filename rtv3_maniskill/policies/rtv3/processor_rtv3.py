"""Pre/post-processing pipelines of the RT-V3 policy (LeRobot's ACT pattern).

The model normalises by itself (egocentric frame + fixed scales), so the normaliser steps are
identities under the config's ``normalization_mapping``; they stay in the pipeline so that
saved processors look like every other LeRobot policy's. The rename and device steps are kept
under their standard names: ``lerobot-eval`` overrides them by name. The features a dataset
stores flat (``features.STORED_FLAT``) pass through unchanged: the policy's batch reader
(``batch.py``) reshapes them.
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import (
    AddBatchDimensionProcessorStep,
    DeviceProcessorStep,
    NormalizerProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    RenameObservationsProcessorStep,
    UnnormalizerProcessorStep,
)
from lerobot.processor.converters import (
    batch_to_transition,
    policy_action_to_transition,
    transition_to_policy_action,
)
from lerobot.processor.core import TransitionKey
from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME

from rtv3_maniskill import features
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config


def make_rtv3_pre_post_processors(
    config: RTV3Config,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Pre-processor: rename -> add batch dim -> device -> (identity) normalise.
    Post-processor: (identity) unnormalise -> CPU."""
    input_steps = [
        RenameObservationsProcessorStep(rename_map={}),
        AddBatchDimensionProcessorStep(),
        DeviceProcessorStep(device=config.device),
        NormalizerProcessorStep(
            features={**config.input_features, **config.output_features},
            norm_map=config.normalization_mapping,
            stats=dataset_stats,
            device=config.device,
        ),
    ]
    output_steps = [
        UnnormalizerProcessorStep(
            features=config.output_features, norm_map=config.normalization_mapping, stats=dataset_stats
        ),
        DeviceProcessorStep(device="cpu"),
    ]
    return (
        PolicyProcessorPipeline[dict[str, Any], dict[str, Any]](
            steps=input_steps, name=POLICY_PREPROCESSOR_DEFAULT_NAME, to_transition=batch_to_rtv3_transition
        ),
        PolicyProcessorPipeline[PolicyAction, PolicyAction](
            steps=output_steps,
            name=POLICY_POSTPROCESSOR_DEFAULT_NAME,
            to_transition=policy_action_to_transition,
            to_output=transition_to_policy_action,
        ),
    )


def batch_to_rtv3_transition(batch: dict[str, Any]):
    """LeRobot's ``batch_to_transition`` that also carries ``target_grasp_index`` through.

    The dataset's target index is privileged training information: the policy never reads
    it as an input, but training needs it for the grasp-subset augmentation (docs/PAPER_DETAILS.md: keep a
    random subset of the candidates, always with the target). LeRobot's default converter
    keeps only ``observation.*``, ``action`` and a few bookkeeping keys.
    """
    transition = batch_to_transition(batch)
    if features.TARGET_GRASP in batch:
        extra = dict(transition.get(TransitionKey.COMPLEMENTARY_DATA) or {})
        extra[features.TARGET_GRASP] = batch[features.TARGET_GRASP]
        transition[TransitionKey.COMPLEMENTARY_DATA] = extra
    return transition
