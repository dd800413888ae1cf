"""Configuration of the RT-V3 prior policy (LeRobot policy type ``rtv3``).

Defaults follow docs/PAPER_DETAILS.md (the authors' constants) and the Trajectron++ training
recipe RT-V3 builds on; the sizes and loss constants a user does not tune are in ``constants.py``.
Outputs of the policy API are always SI: body twists in m/s and rad/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
from lerobot.optim.optimizers import AdamConfig, OptimizerConfig
from lerobot.optim.schedulers import LRSchedulerConfig
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR

from rtv3_maniskill import features as ft
from rtv3_maniskill.policies.rtv3.constants import GRASP_HEADS
from rtv3_maniskill.policies.rtv3.decoder import ROTATION_CONDITIONING_MODES
from rtv3_maniskill.policies.rtv3.schedules import exponential_lr_factor

ENV_STATE = ft.ENV_STATE


@OptimizerConfig.register_subclass("rtv3_adam")
@dataclass
class RTV3AdamConfig(AdamConfig):
    """LeRobot's Adam with PyTorch's fused update (``fused``, which ``AdamConfig.build`` passes on with
    the other fields): one kernel over all 188 parameter tensors instead of a loop over them, the same
    update (about 2 instead of 12 ms per step on one CPU thread)."""

    fused: bool = True


@LRSchedulerConfig.register_subclass("rtv3_exponential")
@dataclass
class RTV3ExponentialSchedulerConfig(LRSchedulerConfig):
    """Per-step exponential decay ``lr_t = lr_0 * max(decay_rate**t, min_lr_ratio)`` (Trajectron++ style)."""

    num_warmup_steps: int | None = None
    decay_rate: float = 0.9999
    min_lr_ratio: float = 0.1

    def build(self, optimizer: Optimizer, num_training_steps: int) -> LambdaLR:
        return LambdaLR(optimizer, exponential_lr_factor(self.decay_rate, self.min_lr_ratio))


@PreTrainedConfig.register_subclass("rtv3")
@dataclass
class RTV3Config(PreTrainedConfig):
    """RT-V3 prior: CVAE over body-twist trajectories conditioned on history, point cloud and grasps.

    Training data: LeRobot loads one dataset row per sample (no ``delta_indices`` windows); the policy
    reads the state history from the row's ``observation.state_history`` and cuts the future actions
    (and, for a dataset without the stored history, the states) from an in-memory copy of the
    dataset's ``action`` / ``observation.state`` columns (``training_cache.py``).

    Input / output structure:
        n_obs_steps: T, states in the history including the current one (docs/PAPER_DETAILS.md: 8).
        horizon: H, predicted future body twists (docs/PAPER_DETAILS.md: 12 steps of ``features.DT``).
        n_action_steps: twists ``select_action`` executes per model call (1 = closed loop, as in the paper).
        num_points: N, point slots of ``observation.point_cloud (N, 6)``; taken from the dataset's features
            when it stores the context keys separately.
        max_grasps: M, grasp slots of ``observation.grasps (M, 9)``; likewise. N and M fix the length of
            the packed ``observation.environment_state`` (``features.environment_state_dim``).
        normalization_mapping: LeRobot's normaliser modes; identities, since the model normalises by
            itself (egocentric frame, fixed scales).
        init_weights_from: a ``pretrained_model`` folder whose weights and training-step counter start
            a new run (fine-tuning with ``--policy.type=rtv3``, which builds the rtv3 pre-processor that
            keeps ``target_grasp_index`` for the grasp-subset augmentation; a pre-processor loaded with
            ``--policy.path`` drops it). Consumed when the policy is built; ``None`` = fresh weights.

    Network (the shipped weights fix these):
        num_maneuver_classes: K, values of the discrete latent ``z``. 10 (RT-V2's choice) rather than
            Trajectron++'s 25: reaching a grasp has fewer distinct manoeuvres than pedestrian motion,
            and every training step decodes all K.
        decoder_hidden_dim: state size of the GRU decoder.
        grasp_dim: width of the grasp transformer (``constants.GRASP_HEADS`` heads).
        point_patch_size: points per attention patch of the point-cloud encoder (adds no parameters).
        point_stem_poolings: parameter-free grid poolings (2x coarser each, features max-pooled,
            coordinates averaged) before the first stage of the point-cloud encoder. 1: the first stage
            attends over one point per 15 mm voxel, ~30 % faster ``select_action`` on CPU with N = 2048
            at no measured cost; 0: the authors' layout (every input point), which the shipped weights
            were trained with. Adds no parameters, so weights move between the two.
        transformer_dropout: dropout probability in the grasp and point transformers (training only).

    Ablations (paper Table I):
        use_grasp_encoder: encode the grasp candidates (False: "w/o grasp encoder").
        use_point_encoder: encode the point cloud (False: "w/o point-cloud encoder").
        factorized_rotation: ``p(v | h, z) p(w | h, z, v)`` (Eq. velocitygmm / rotgmm); False = one joint
            6-D Gaussian per step ("6D pred").

    Training (the decoder always runs free, reading its own most likely twist, as at inference):
        kl_weight: beta, the final weight of ``KL(q || p)`` (annealed from 0 along a sigmoid).
        history_noise_translation / history_noise_rotation: half-width (m / rad) of the uniform se(3)
            noise on the past poses (not the current one); 0 disables.
        twist_noise_linear / twist_noise_angular: half-width (m/s / rad/s) of the uniform noise on the
            history's body twists, the current one (the decoder's ``a_{-1}``) included; the targets stay
            clean, so the prior learns to return to the expert's motion from a perturbed one. 0 disables.
        history_rotation_resample_prob: probability that a sample's past turn is replaced by a random
            constant one (up to ``constants.RESAMPLED_TURN_RATE`` rad/s per axis, ending at the current
            orientation; ``egocentric.resample_past_rotation``), so that the prior reads its turn from
            the goal instead of continuing its own. 0 disables.
        rotation_conditioning: the translation the rotation head ``p(w | h, z, v)`` is evaluated at in
            training: "demonstrated" (the expert's v) or "sampled" (a draw from the predicted
            ``p(v | h, z)``, the paper's two-stage sampling; at inference the head only sees predicted
            or fused translations).

    Optimiser (Adam; the learning rate decays per step):
        optimizer_lr: initial learning rate.
        optimizer_min_lr: floor of the decayed learning rate.
        optimizer_lr_decay: per-step factor, ``lr_t = max(lr * decay**t, min_lr)``.
        optimizer_weight_decay: Adam's L2 weight decay.
        optimizer_grad_clip_norm: gradient-norm clip.
    """

    # Input / output structure.
    n_obs_steps: int = ft.HISTORY_STEPS
    horizon: int = ft.HORIZON_STEPS
    n_action_steps: int = 1
    num_points: int = ft.DEFAULT_NUM_POINTS
    max_grasps: int = ft.DEFAULT_MAX_GRASPS
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "STATE": NormalizationMode.IDENTITY,
            "ENV": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )
    init_weights_from: str | None = None

    # Network.
    num_maneuver_classes: int = 10
    decoder_hidden_dim: int = 128
    grasp_dim: int = 128
    point_patch_size: int = 120
    point_stem_poolings: int = 1
    transformer_dropout: float = 0.1

    # Ablations.
    use_grasp_encoder: bool = True
    use_point_encoder: bool = True
    factorized_rotation: bool = True

    # Training.
    kl_weight: float = 100.0
    history_noise_translation: float = 0.007
    history_noise_rotation: float = 0.0035
    twist_noise_linear: float = 0.0
    twist_noise_angular: float = 0.0
    history_rotation_resample_prob: float = 0.0
    rotation_conditioning: str = "demonstrated"

    # Optimiser.
    optimizer_lr: float = 1e-3
    optimizer_min_lr: float = 1e-4
    optimizer_lr_decay: float = 0.9999
    optimizer_weight_decay: float = 0.0
    optimizer_grad_clip_norm: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("n_obs_steps", "horizon", "n_action_steps", "num_points", "max_grasps", "num_maneuver_classes",
                     "decoder_hidden_dim", "grasp_dim", "point_patch_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"RTV3Config.{name} must be a positive integer, got {value!r}")
        if self.n_action_steps > self.horizon:
            raise ValueError(
                f"n_action_steps ({self.n_action_steps}) cannot exceed the predicted horizon ({self.horizon})"
            )
        if self.grasp_dim % GRASP_HEADS:
            raise ValueError(f"grasp_dim ({self.grasp_dim}) must be a multiple of the {GRASP_HEADS} grasp heads")
        if isinstance(self.point_stem_poolings, bool) or not isinstance(self.point_stem_poolings, int) \
                or self.point_stem_poolings < 0:
            raise ValueError("RTV3Config.point_stem_poolings must be an integer >= 0, "
                             f"got {self.point_stem_poolings!r}")
        for name in ("transformer_dropout", "history_rotation_resample_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"RTV3Config.{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("kl_weight", "history_noise_translation", "history_noise_rotation", "twist_noise_linear",
                     "twist_noise_angular", "optimizer_weight_decay"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"RTV3Config.{name} must be a finite number >= 0, got {value}")
        if self.rotation_conditioning not in ROTATION_CONDITIONING_MODES:
            raise ValueError(
                f"rotation_conditioning must be one of {ROTATION_CONDITIONING_MODES}, "
                f"got {self.rotation_conditioning!r}"
            )
        if not 0 < self.optimizer_min_lr <= self.optimizer_lr:
            raise ValueError("need 0 < optimizer_min_lr <= optimizer_lr")
        if not 0 < self.optimizer_lr_decay <= 1:
            raise ValueError(f"optimizer_lr_decay must be in (0, 1], got {self.optimizer_lr_decay}")
        if not self.optimizer_grad_clip_norm > 0:
            raise ValueError(f"optimizer_grad_clip_norm must be > 0, got {self.optimizer_grad_clip_norm}")

    # ------------------------------------------------------------------ LeRobot hooks

    def get_optimizer_preset(self) -> RTV3AdamConfig:
        return RTV3AdamConfig(
            lr=self.optimizer_lr,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> RTV3ExponentialSchedulerConfig:
        return RTV3ExponentialSchedulerConfig(
            decay_rate=self.optimizer_lr_decay, min_lr_ratio=self.optimizer_min_lr / self.optimizer_lr
        )

    @property
    def observation_delta_indices(self) -> None:
        """No history window: each sample is one dataset row (the history is its stored
        ``observation.state_history``, or is cut from the training cache)."""
        return None

    @property
    def action_delta_indices(self) -> None:
        """No action window: the policy cuts ``a_0 .. a_{H-1}`` from the training cache by the batch's
        frame ``index`` (``training_cache.py``), ~13x less data per sample than LeRobot's H-frame window."""
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def default_input_features(self) -> dict[str, PolicyFeature]:
        """The ``features.py`` schema with separate context keys."""
        return {
            ft.STATE: PolicyFeature(type=FeatureType.STATE, shape=(ft.STATE_DIM,)),
            ft.POINT_CLOUD: PolicyFeature(type=FeatureType.STATE, shape=(self.num_points, 6)),
            ft.POINT_CLOUD_MASK: PolicyFeature(type=FeatureType.STATE, shape=(self.num_points,)),
            ft.GRASPS: PolicyFeature(type=FeatureType.STATE, shape=(self.max_grasps, ft.GRASP_DIM)),
            ft.GRASPS_MASK: PolicyFeature(type=FeatureType.STATE, shape=(self.max_grasps,)),
        }

    def default_output_features(self) -> dict[str, PolicyFeature]:
        return {ft.ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(6,))}

    def validate_features(self) -> None:
        """Check the dataset/env features against the ``features.py`` schema (shapes as tuples)."""
        inputs = dict(self.input_features or {})
        outputs = dict(self.output_features or {})

        def shape_of(features: dict[str, PolicyFeature], key: str) -> tuple[int, ...]:
            return tuple(int(s) for s in features[key].shape)

        if ft.STATE not in inputs:
            raise ValueError(f"RT-V3 needs the input feature '{ft.STATE}' (shape ({ft.STATE_DIM},))")
        if shape_of(inputs, ft.STATE) != (ft.STATE_DIM,):
            raise ValueError(f"'{ft.STATE}' must have shape ({ft.STATE_DIM},), got {shape_of(inputs, ft.STATE)}")
        if ft.ACTION not in outputs or shape_of(outputs, ft.ACTION) != (6,):
            got = shape_of(outputs, ft.ACTION) if ft.ACTION in outputs else "missing"
            raise ValueError(f"RT-V3 needs the output feature '{ft.ACTION}' with shape (6,), got {got}")
        context_keys = (ft.POINT_CLOUD, ft.POINT_CLOUD_MASK, ft.GRASPS, ft.GRASPS_MASK)
        present = [k for k in context_keys if k in inputs]
        if present:
            missing = [k for k in context_keys if k not in inputs]
            if missing:
                raise ValueError(f"context features {present} given but {missing} missing")
            expected = {
                ft.POINT_CLOUD: (self.num_points, 6),
                ft.POINT_CLOUD_MASK: (self.num_points,),
                ft.GRASPS: (self.max_grasps, ft.GRASP_DIM),
                ft.GRASPS_MASK: (self.max_grasps,),
            }
            for key, want in expected.items():
                got = shape_of(inputs, key)
                # datasets store the 2-D context features flat (features.STORED_FLAT)
                if got != want and not (key in ft.STORED_FLAT and got == ft.stored_shape(key, want[0])):
                    raise ValueError(
                        f"'{key}' has shape {shape_of(inputs, key)}, expected {want} "
                        f"(num_points={self.num_points}, max_grasps={self.max_grasps})"
                    )
        elif ENV_STATE in inputs:
            want = (ft.environment_state_dim(self.num_points, self.max_grasps),)
            if shape_of(inputs, ENV_STATE) != want:
                raise ValueError(
                    f"'{ENV_STATE}' has shape {shape_of(inputs, ENV_STATE)}, expected {want} = "
                    f"features.environment_state_dim(num_points={self.num_points}, max_grasps={self.max_grasps})"
                )
        else:
            raise ValueError(
                f"RT-V3 needs the scene context: either {list(context_keys)} or '{ENV_STATE}' (packed)"
            )
