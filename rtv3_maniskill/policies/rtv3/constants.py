"""Fixed sizes and training constants of the RT-V3 prior (docs/PAPER_DETAILS.md, Trajectron++'s recipe).

:class:`~rtv3_maniskill.policies.rtv3.configuration_rtv3.RTV3Config` holds what a user tunes; these
are the rest. The network sizes fix the shapes of the shipped weights. Inside the network every
translational velocity is multiplied by :data:`TRANSLATION_SCALE` and every position by
:data:`POSITION_SCALE` ("network units"); the policy's inputs and outputs are SI (m, rad, m/s, rad/s).
"""

from __future__ import annotations

# ---------------------------------------------------------------------- network sizes

HISTORY_HIDDEN_DIM = 32
"""Hidden size of the LSTM over the past dynamics ``x_{-T+1:0}`` (its last state is ``h0_d``), and of
the query the context decoders read."""
FUTURE_HIDDEN_DIM = 32
"""Hidden size of each direction of the BiLSTM over the future dynamics ``x_{1:H}`` (``h+``, training only)."""
PRIOR_HIDDEN_DIM = 32
"""Hidden units of the maneuver prior ``p(z | h0)`` (one hidden layer); the posterior ``q(z | h_H)`` is linear."""
DECODER_CONTEXT_DIM = 64
"""Size of the projection of ``h0`` the GRU decoder reads at every step."""
HEAD_HIDDEN_DIM = 128
"""Hidden units of each Gaussian head (translation, rotation, or the joint 6-D one)."""

GRASP_HEADS = 4
"""Attention heads of the grasp transformer (divides ``RTV3Config.grasp_dim``)."""
GRASP_ENCODER_LAYERS = 2
"""Self-attention layers over the grasp set."""
GRASP_DECODER_LAYERS = 2
"""Decoder layers whose single query is ``h0_d``."""
GRASP_FEEDFORWARD_DIM = 256
"""Feed-forward width of the grasp transformer layers."""
GRASP_FEATURE_DIM = 11
"""Per-grasp input: the 6-D log map of ``T_0^-1 G``, the grasp position in the EE frame (3), width and score."""

POINT_CHANNELS = (32, 32, 64)
"""Channels of the three PTv3-style stages of the point-cloud encoder (the last is ``h_pcl``'s size)."""
POINT_HEADS = (2, 4, 4)
"""Attention heads of each stage (each divides its stage's channels)."""
POINT_DEPTHS = (1, 1, 1)
"""Transformer blocks per stage."""
POINT_GRID_SIZE = 0.0075
"""Voxel edge (m) of the first stage's grid; doubled at each grid pooling."""
POINT_DECODER_HEADS = 4
"""Heads of the point-cloud decoder queried by ``h0_d``."""
POINT_DECODER_LAYERS = 1
"""Layers of that decoder."""

# ---------------------------------------------------------------------- scaling

TRANSLATION_SCALE = 5.0
"""Multiplies translational velocities (m/s) in and out of the network (docs/PAPER_DETAILS.md: 5)."""
POSITION_SCALE = 10.0
"""Multiplies positions (m) fed to the network: history poses, points, grasps, gripper widths."""
LOG_SIGMA_MIN, LOG_SIGMA_MAX = -6.0, 3.0
"""Clamp of every predicted log standard deviation (network units)."""

# ---------------------------------------------------------------------- loss (negative ELBO)

KL_WEIGHT_START = 0.0
"""beta at training step 0; it rises along a sigmoid to ``RTV3Config.kl_weight``."""
KL_CROSSOVER = 400
"""Step (of the policy's own counter ``train_step``) at which beta is half-way."""
KL_SIGMOID_DIVISOR = 4.0
"""The sigmoid's width is ``KL_CROSSOVER / KL_SIGMOID_DIVISOR`` steps."""
KL_MIN = 0.07
"""Free bits: ``KL(q || p)`` is clamped below at this many nats."""
Z_LOGIT_CLIP_START, Z_LOGIT_CLIP_FINAL = 0.05, 5.0
"""The logits of ``p(z | h0)`` and ``q(z | h_H)`` are mean-centred and clipped to ``+-c``; ``c`` is
annealed from the first to the second along a sigmoid."""
Z_LOGIT_CLIP_CROSSOVER, Z_LOGIT_CLIP_DIVISOR = 300, 5.0
"""Half-way step and width divisor of that sigmoid."""
LOG_PROB_CLAMP = 6.0
"""Upper clamp of each per-step 3-D Gaussian log-likelihood (translation, rotation); the joint 6-D
one ("6D pred") is clamped at twice this."""
MUTUAL_INFORMATION_WEIGHT = 1.0
"""Weight of the batch estimate of ``I(x; z)`` under p subtracted from the loss."""

# ---------------------------------------------------------------------- training augmentation

GRASP_SUBSET_MIN = 1
"""Smallest grasp subset the grasp-subset augmentation keeps (the authors use 10; 1 also covers the
planning benchmark, which shows the policy only its target)."""
RESAMPLED_TURN_RATE = 1.0
"""Bound (rad/s, per axis) of the constant turn that replaces a resampled history's past rotation
(``RTV3Config.history_rotation_resample_prob``)."""
