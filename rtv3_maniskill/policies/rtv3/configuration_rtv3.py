"""Configuration of the RT-V3 prior policy (LeRobot policy type ``rtv3``).

Defaults follow docs/PAPER_DETAILS.md (the authors' constants) and the
Trajectron++ training recipe RT-V3 builds on. Every translational velocity the network
sees or predicts is multiplied by ``translation_scale`` (the authors use 5); outputs of
the policy API are always unscaled (m/s, rad/s).
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

    Input/output structure:
        n_obs_steps: T, history length incl. the current step (docs/PAPER_DETAILS.md: 8).
        horizon: H, predicted future steps (docs/PAPER_DETAILS.md: 12).
        n_action_steps: actions executed per model call by ``select_action`` (1 = closed loop, as in the paper).
        num_points / max_grasps: N and M of the fixed-size context arrays (``features.py``); they fix the
            length of the packed ``observation.environment_state``.

    Latent and decoder:
        num_maneuver_classes: K. 10 (RT-V2's choice) rather than Trajectron++'s 25: the grasp-reaching
            task has fewer distinct manoeuvres than pedestrian motion, and training enumerates all K.
        decoder_hidden_dim: GRU decoder state (128). decoder_context_dim: size of the h0 projection fed to
            the GRU each step. head_hidden_dim: hidden units of the Gaussian heads.
        prior_hidden_dim: hidden units of p(z|h0) (32). q(z|h_H) is linear.
        factorized_rotation: True = p(v|h,z) p(w|h,z,v) (Eq. velocitygmm/rotgmm); False = one joint 6-D
            Gaussian per step (the paper's "6D pred" ablation).

    Encoders (docs/PAPER_DETAILS.md sizes):
        history_hidden_dim / future_hidden_dim: LSTM / BiLSTM hidden sizes (32).
        grasp_*: transformer encoder d=128, 4 heads, 2 layers + 2-layer decoder queried by h0_d.
        point_channels / point_heads / point_depths: the three PTv3-style stages (32/32/C, heads 2/4/4,
            depth 1); point_patch_size 120; point_grid_size 7.5 mm (doubled at each grid pooling).
        point_stem_poolings: parameter-free grid poolings (2x coarser each, features max-pooled, coordinates
            averaged) between the embedding and the first stage. 1 (default): the first stage attends over one
            point per 15 mm voxel (a scan voxelised at 7.5 mm has ~3x fewer), which takes ~30 % off
            ``select_action`` on CPU with all N = 2048 slots filled at no measured cost in prediction or planning
            (README); 0: the authors' layout (docs/PAPER_DETAILS.md), the first stage attends over every input point.
            Adds no parameters, so weights move between the two.
        point_decoder_heads / point_decoder_layers: decoder queried by h0_d (4 heads, 1 layer).
        use_grasp_encoder / use_point_encoder: ablation switches (paper Table I).

    Scaling:
        translation_scale: multiplies translational velocities in and out of the network (docs/PAPER_DETAILS.md: 5).
        position_scale: multiplies positions fed to the network (poses, points, grasps), m -> network units.
        log_sigma_min / log_sigma_max: clamp of predicted log standard deviations (network units).

    Loss (Trajectron++ recipe, docs/PAPER_DETAILS.md):
        kl_weight: beta = 100, annealed with a sigmoid from kl_weight_start, centred at kl_crossover steps,
            width kl_crossover / kl_sigmoid_divisor steps.
        kl_min: KL(q||p) is clamped below at 0.07 (free bits).
        z_logit_clip_*: logits of p and q are mean-centred and clipped to +-c, c annealed 0.05 -> 5.
        log_prob_clamp: each per-step 3-D Gaussian log-likelihood (translation, rotation) is clamped at
            6 (the joint 6-D one at 12).
        mutual_information_weight: weight of I_p subtracted from the loss (Trajectron++: 1).
        history_noise_translation / _rotation: training-time uniform se(3) noise (m, rad) applied to the
            past poses (not the current one) (docs/PAPER_DETAILS.md augmentation). 0 disables.
        twist_noise_linear / _angular: training-time uniform noise (m/s, rad/s) on the history's body
            twists, the current one (a_{-1}, fed to the decoder) included; the targets stay clean, so
            the prior learns to return to the expert's motion from a perturbed one instead of copying
            the last twist (closed loop, its own errors come back as the current twist). 0 disables.
        history_rotation_resample_prob / _speed: training-time probability that a sample's past
            orientations (and the history's angular twists, the decoder's a_{-1} included) are replaced
            by a constant turn of up to ``_speed`` rad/s per axis (``egocentric.resample_past_rotation``),
            so that the past turn does not tell the next one. The targets stay the expert's. Without it
            the prior continues its own past turn in closed loop. 0 disables.
        rotation_conditioning: what the rotation head p(w | h, z, v) is conditioned on in training:
            "demonstrated" = the demonstrated v; "sampled" = a translation drawn from the predicted
            p(v | h, z) (the paper's two-stage sampling, a regulariser: at inference the head is
            evaluated at predicted or fused translations, never at the true one).

    Optimiser: Adam, lr 1e-3 decaying exponentially (0.9999 per step) to 1e-4, grad clip 1.0.
    """

    # Input / output structure.
    n_obs_steps: int = ft.HISTORY_STEPS
    horizon: int = ft.HORIZON_STEPS
    n_action_steps: int = 1
    num_points: int = ft.DEFAULT_NUM_POINTS
    max_grasps: int = ft.DEFAULT_MAX_GRASPS

    # The model normalises egocentrically itself; the standard normaliser steps stay in the pipeline
    # as identities.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "STATE": NormalizationMode.IDENTITY,
            "ENV": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    init_weights_from: str | None = None
    """Checkpoint folder whose weights (and training-step counter) initialise a new run: fine-tuning
    with ``--policy.type=rtv3``, so the rtv3 pre-processor (which keeps ``target_grasp_index`` for the
    grasp-subset augmentation) is built; ``--policy.path`` would load a saved pipeline that drops it."""

    # Latent variable and decoder.
    num_maneuver_classes: int = 10
    prior_hidden_dim: int = 32
    decoder_hidden_dim: int = 128
    decoder_context_dim: int = 64
    head_hidden_dim: int = 128
    factorized_rotation: bool = True

    # Dynamics encoders.
    history_hidden_dim: int = 32
    future_hidden_dim: int = 32

    # Grasp encoder.
    use_grasp_encoder: bool = True
    grasp_dim: int = 128
    grasp_heads: int = 4
    grasp_encoder_layers: int = 2
    grasp_decoder_layers: int = 2
    grasp_feedforward_dim: int = 256
    grasp_subset_min: int = 1
    """Training augmentation (docs/PAPER_DETAILS.md): each sample keeps a random subset of grasp candidates of size
    grasp_subset_min..all, always with the target. The authors use 10; 1 also covers the planning
    benchmark, which shows the policy only its target grasp."""

    # Point cloud encoder (PTv3-style).
    use_point_encoder: bool = True
    point_channels: tuple[int, ...] = (32, 32, 64)
    point_heads: tuple[int, ...] = (2, 4, 4)
    point_depths: tuple[int, ...] = (1, 1, 1)
    point_patch_size: int = 120
    point_grid_size: float = 0.0075
    point_stem_poolings: int = 1
    point_decoder_heads: int = 4
    point_decoder_layers: int = 1

    transformer_dropout: float = 0.1

    # Scaling.
    translation_scale: float = 5.0
    position_scale: float = 10.0
    log_sigma_min: float = -6.0
    log_sigma_max: float = 3.0

    # Loss.
    kl_weight: float = 100.0
    kl_weight_start: float = 0.0
    kl_crossover: int = 400
    kl_sigmoid_divisor: float = 4.0
    kl_min: float = 0.07
    z_logit_clip_start: float = 0.05
    z_logit_clip_final: float = 5.0
    z_logit_clip_crossover: int = 300
    z_logit_clip_divisor: float = 5.0
    log_prob_clamp: float = 6.0
    mutual_information_weight: float = 1.0
    history_noise_translation: float = 0.007
    history_noise_rotation: float = 0.0035
    twist_noise_linear: float = 0.0
    twist_noise_angular: float = 0.0
    history_rotation_resample_prob: float = 0.0
    history_rotation_resample_speed: float = 1.0
    rotation_conditioning: str = "demonstrated"

    # Optimiser preset.
    optimizer_lr: float = 1e-3
    optimizer_min_lr: float = 1e-4
    optimizer_lr_decay: float = 0.9999
    optimizer_weight_decay: float = 0.0
    optimizer_grad_clip_norm: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        self.point_channels = tuple(int(c) for c in self.point_channels)
        self.point_heads = tuple(int(h) for h in self.point_heads)
        self.point_depths = tuple(int(d) for d in self.point_depths)
        positive_ints = {
            "n_obs_steps": self.n_obs_steps,
            "horizon": self.horizon,
            "n_action_steps": self.n_action_steps,
            "num_points": self.num_points,
            "max_grasps": self.max_grasps,
            "grasp_subset_min": self.grasp_subset_min,
            "num_maneuver_classes": self.num_maneuver_classes,
            "prior_hidden_dim": self.prior_hidden_dim,
            "decoder_hidden_dim": self.decoder_hidden_dim,
            "decoder_context_dim": self.decoder_context_dim,
            "head_hidden_dim": self.head_hidden_dim,
            "history_hidden_dim": self.history_hidden_dim,
            "future_hidden_dim": self.future_hidden_dim,
            "grasp_dim": self.grasp_dim,
            "grasp_heads": self.grasp_heads,
            "grasp_encoder_layers": self.grasp_encoder_layers,
            "grasp_decoder_layers": self.grasp_decoder_layers,
            "grasp_feedforward_dim": self.grasp_feedforward_dim,
            "point_patch_size": self.point_patch_size,
            "point_decoder_heads": self.point_decoder_heads,
            "point_decoder_layers": self.point_decoder_layers,
        }
        for name, value in positive_ints.items():
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"RTV3Config.{name} must be a positive integer, got {value!r}")
        if self.n_action_steps > self.horizon:
            raise ValueError(
                f"n_action_steps ({self.n_action_steps}) cannot exceed the predicted horizon ({self.horizon})"
            )
        if self.grasp_dim % self.grasp_heads:
            raise ValueError(f"grasp_dim ({self.grasp_dim}) must be divisible by grasp_heads ({self.grasp_heads})")
        if not (len(self.point_channels) == len(self.point_heads) == len(self.point_depths) >= 1):
            raise ValueError(
                "point_channels, point_heads and point_depths need one entry per stage, got "
                f"{self.point_channels}, {self.point_heads}, {self.point_depths}"
            )
        for c, h in zip(self.point_channels, self.point_heads):
            if c < 1 or h < 1 or c % h:
                raise ValueError(f"point stage with {c} channels and {h} heads: channels must be a multiple of heads")
        if self.point_channels[-1] % self.point_decoder_heads:
            raise ValueError(
                f"last point stage channels ({self.point_channels[-1]}) must be divisible by "
                f"point_decoder_heads ({self.point_decoder_heads})"
            )
        if any(d < 1 for d in self.point_depths):
            raise ValueError(f"point_depths must be >= 1, got {self.point_depths}")
        if not isinstance(self.point_stem_poolings, int) or self.point_stem_poolings < 0:
            raise ValueError("RTV3Config.point_stem_poolings must be an integer >= 0, "
                             f"got {self.point_stem_poolings!r}")
        if not self.point_grid_size > 0:
            raise ValueError(f"point_grid_size must be > 0 (metres), got {self.point_grid_size}")
        for name in ("translation_scale", "position_scale", "kl_sigmoid_divisor", "z_logit_clip_divisor"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"RTV3Config.{name} must be a finite positive number, got {value}")
        if not self.log_sigma_min < self.log_sigma_max:
            raise ValueError(f"log_sigma_min ({self.log_sigma_min}) must be < log_sigma_max ({self.log_sigma_max})")
        for name in ("kl_weight", "kl_weight_start", "kl_min", "mutual_information_weight",
                     "history_noise_translation", "history_noise_rotation", "twist_noise_linear",
                     "twist_noise_angular", "transformer_dropout", "history_rotation_resample_speed",
                     "optimizer_weight_decay"):
            if getattr(self, name) < 0:
                raise ValueError(f"RTV3Config.{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.history_rotation_resample_prob <= 1.0:
            raise ValueError("RTV3Config.history_rotation_resample_prob must be in [0, 1], "
                             f"got {self.history_rotation_resample_prob}")
        if self.rotation_conditioning not in ROTATION_CONDITIONING_MODES:
            raise ValueError(
                f"rotation_conditioning must be one of {ROTATION_CONDITIONING_MODES}, "
                f"got {self.rotation_conditioning!r}"
            )
        if not 0 < self.z_logit_clip_start <= self.z_logit_clip_final:
            raise ValueError("need 0 < z_logit_clip_start <= z_logit_clip_final")
        if not 0 < self.optimizer_min_lr <= self.optimizer_lr:
            raise ValueError("need 0 < optimizer_min_lr <= optimizer_lr")
        if not 0 < self.optimizer_lr_decay <= 1:
            raise ValueError(f"optimizer_lr_decay must be in (0, 1], got {self.optimizer_lr_decay}")

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
