"""The RT-V3 prior network (paper, Sec. III-IV), independent of LeRobot's policy plumbing.

Notation follows the paper: ``x_t`` per-step dynamics, ``h0_d`` past-dynamics encoding,
``h_pcl`` / ``h_grasp`` context encodings, ``h0 = [h0_d, h_pcl, h_grasp]``, ``h+`` future
encoding, ``z`` the maneuver class (one-hot over K), ``a_t = [v_t, w_t]`` body twists.
Inside the network translational velocities are multiplied by ``constants.TRANSLATION_SCALE`` and
positions by ``constants.POSITION_SCALE``; every public method here takes and returns SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn

from rtv3_maniskill import features, se3
from rtv3_maniskill.policies.rtv3 import egocentric
from rtv3_maniskill.policies.rtv3.batch import RTV3Inputs
from rtv3_maniskill.policies.rtv3.constants import (
    DECODER_CONTEXT_DIM,
    FUTURE_HIDDEN_DIM,
    GRASP_DECODER_LAYERS,
    GRASP_ENCODER_LAYERS,
    GRASP_FEATURE_DIM,
    GRASP_FEEDFORWARD_DIM,
    GRASP_HEADS,
    HEAD_HIDDEN_DIM,
    HISTORY_HIDDEN_DIM,
    KL_CROSSOVER,
    KL_MIN,
    KL_SIGMOID_DIVISOR,
    KL_WEIGHT_START,
    LOG_PROB_CLAMP,
    LOG_SIGMA_MAX,
    LOG_SIGMA_MIN,
    MUTUAL_INFORMATION_WEIGHT,
    POINT_CHANNELS,
    POINT_DECODER_HEADS,
    POINT_DECODER_LAYERS,
    POINT_DEPTHS,
    POINT_GRID_SIZE,
    POINT_HEADS,
    POSITION_SCALE,
    PRIOR_HIDDEN_DIM,
    RESAMPLED_TURN_RATE,
    TRANSLATION_SCALE,
    Z_LOGIT_CLIP_CROSSOVER,
    Z_LOGIT_CLIP_DIVISOR,
    Z_LOGIT_CLIP_FINAL,
    Z_LOGIT_CLIP_START,
)
from rtv3_maniskill.policies.rtv3.context_encoders import GraspEncoder, PointCloudEncoder
from rtv3_maniskill.policies.rtv3.decoder import DecoderStart, TrajectoryDecoder
from rtv3_maniskill.policies.rtv3.gaussians import JointGaussian
from rtv3_maniskill.policies.rtv3.latent import (
    ManeuverPosterior,
    ManeuverPrior,
    kl_categorical,
    mutual_information,
    sigmoid_anneal,
)
from rtv3_maniskill.twist_mixture import TwistMixture

if TYPE_CHECKING:  # the model reads its config's fields only: it also trains without LeRobot (compact_training.py)
    from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config


@dataclass
class Encoding:
    """Per-sample encodings: ``h0 (B, D)`` and ``a_{-1}`` = current twist ``(B, 6)`` (network units)."""

    h0: torch.Tensor
    prev_action: torch.Tensor


class RTV3Model(nn.Module):
    """History LSTM + grasp / point-cloud transformers -> h0 -> p(z|h0) -> GRU decoder (see decoder.py)."""

    def __init__(self, config: RTV3Config):
        super().__init__()
        self.config = c = config
        self.history_encoder = nn.LSTM(12, HISTORY_HIDDEN_DIM, batch_first=True)
        self.future_encoder = nn.LSTM(12, FUTURE_HIDDEN_DIM, batch_first=True, bidirectional=True)
        h0_dim = HISTORY_HIDDEN_DIM
        self.point_encoder: PointCloudEncoder | None = None
        if c.use_point_encoder:
            self.point_encoder = PointCloudEncoder(
                in_dim=6, query_dim=HISTORY_HIDDEN_DIM, channels=POINT_CHANNELS, heads=POINT_HEADS,
                depths=POINT_DEPTHS, patch_size=c.point_patch_size, grid_size=POINT_GRID_SIZE,
                position_scale=POSITION_SCALE, decoder_heads=POINT_DECODER_HEADS,
                decoder_layers=POINT_DECODER_LAYERS, dropout=c.transformer_dropout,
                stem_poolings=c.point_stem_poolings,
            )
            h0_dim += self.point_encoder.out_dim
        self.grasp_encoder: GraspEncoder | None = None
        if c.use_grasp_encoder:
            self.grasp_encoder = GraspEncoder(
                in_dim=GRASP_FEATURE_DIM, query_dim=HISTORY_HIDDEN_DIM, dim=c.grasp_dim,
                heads=GRASP_HEADS, encoder_layers=GRASP_ENCODER_LAYERS, decoder_layers=GRASP_DECODER_LAYERS,
                feedforward=GRASP_FEEDFORWARD_DIM, dropout=c.transformer_dropout,
            )
            h0_dim += self.grasp_encoder.out_dim
        self.h0_dim = h0_dim
        k = c.num_maneuver_classes
        self.maneuver_prior = ManeuverPrior(h0_dim, PRIOR_HIDDEN_DIM, k)
        self.maneuver_posterior = ManeuverPosterior(h0_dim + 2 * FUTURE_HIDDEN_DIM, k)
        self.decoder = TrajectoryDecoder(
            context_dim=h0_dim, num_classes=k, hidden_dim=c.decoder_hidden_dim,
            context_proj_dim=DECODER_CONTEXT_DIM, head_hidden_dim=HEAD_HIDDEN_DIM,
            factorized_rotation=c.factorized_rotation, log_sigma_min=LOG_SIGMA_MIN, log_sigma_max=LOG_SIGMA_MAX,
        )

    # ------------------------------------------------------------------------- scaling

    @staticmethod
    def _twist_in(twist: torch.Tensor) -> torch.Tensor:
        """SI twist ``(..., 6)`` -> network units (v times ``TRANSLATION_SCALE``)."""
        return torch.cat([twist[..., :3] * TRANSLATION_SCALE, twist[..., 3:]], -1)

    @staticmethod
    def _twist_out(twist: torch.Tensor) -> torch.Tensor:
        return torch.cat([twist[..., :3] / TRANSLATION_SCALE, twist[..., 3:]], -1)

    def _dynamics_in(self, x: torch.Tensor) -> torch.Tensor:
        """``x_t (..., 12)`` SI -> network units: pose-log translation x position scale, twist v x translation scale."""
        return torch.cat([x[..., :3] * POSITION_SCALE, x[..., 3:6], self._twist_in(x[..., 6:])], -1)

    def clip_and_beta(self, step: int) -> tuple[float, float]:
        """Annealed logit clip and KL weight beta at training step ``step`` (sigmoid schedules)."""
        clip = sigmoid_anneal(step, Z_LOGIT_CLIP_START, Z_LOGIT_CLIP_FINAL, Z_LOGIT_CLIP_CROSSOVER,
                              Z_LOGIT_CLIP_DIVISOR)
        beta = sigmoid_anneal(step, KL_WEIGHT_START, self.config.kl_weight, KL_CROSSOVER, KL_SIGMOID_DIVISOR)
        return clip, beta

    # ------------------------------------------------------------------------- encoders

    def encode(self, inputs: RTV3Inputs, augment: bool = False) -> Encoding:
        """``h0 = [h0_d, h_pcl, h_grasp]`` with every input in the current EE frame."""
        c = self.config
        states = inputs.states
        poses = egocentric.state_poses(states)  # (B, T, 4, 4) world
        twists = states[..., features.EE_TWIST]
        if augment and poses.shape[1] > 1 and c.history_rotation_resample_prob > 0:
            selected = torch.rand(poses.shape[0], device=poses.device) < c.history_rotation_resample_prob
            poses, twists = egocentric.resample_past_rotation(poses, twists, selected, RESAMPLED_TURN_RATE,
                                                              features.DT)
        if augment and poses.shape[1] > 1 and (c.history_noise_translation > 0 or c.history_noise_rotation > 0):
            past = egocentric.perturb_poses(poses[:, :-1], c.history_noise_translation, c.history_noise_rotation)
            poses = torch.cat([past, poses[:, -1:]], 1)
        current = poses[:, -1]  # T_0
        relative = se3.relative_transform(current[:, None], poses)  # T_0^-1 T_t, (B, T, 4, 4)
        ctx = inputs.context
        grasp_relative = None
        if self.grasp_encoder is not None:
            grasp_relative = egocentric.grasps_in_frame(current, ctx.grasps)  # T_0^-1 G, (B, M, 4, 4)
            relative = torch.cat([relative, grasp_relative], 1)
        logs = se3.se3_log(relative)  # one batched log map for history and grasps
        steps = poses.shape[1]
        if augment and (c.twist_noise_linear > 0 or c.twist_noise_angular > 0):
            twists = egocentric.perturb_twists(twists, c.twist_noise_linear, c.twist_noise_angular)
        x = egocentric.history_dynamics(relative[:, :steps], twists, logs[:, :steps])  # x_{-T+1:0}
        _, (h_last, _) = self.history_encoder(self._dynamics_in(x))
        h0_d = h_last[-1]  # h0_d = LSTM(x_{-T+1:0})
        parts = [h0_d]
        if self.point_encoder is not None:
            xyz = egocentric.points_in_frame(current, ctx.point_cloud[..., :3])  # T_0^-1 P
            feat = torch.cat([xyz * POSITION_SCALE, ctx.point_cloud[..., 3:6]], -1)
            parts.append(self.point_encoder(xyz, feat, ctx.point_mask, h0_d))  # h_pcl
        if grasp_relative is not None:
            log_map = logs[:, steps:]
            feats = [log_map[..., :3] * POSITION_SCALE, log_map[..., 3:], grasp_relative[..., :3, 3] * POSITION_SCALE,
                     ctx.grasps[..., 7:8] * POSITION_SCALE, ctx.grasps[..., 8:9]]  # GRASP_FEATURE_DIM
            valid = ctx.grasp_mask
            grasp_feat = torch.where(valid[..., None], torch.cat(feats, -1), 0.0)
            parts.append(self.grasp_encoder(grasp_feat, valid, h0_d))  # h_grasp
        return Encoding(h0=torch.cat(parts, -1), prev_action=self._twist_in(x[:, -1, 6:]))

    def encode_future(self, actions: torch.Tensor) -> torch.Tensor:
        """``h+ = BiLSTM(x_{1:H})`` from the action window ``(B, H, 6)`` SI -> ``(B, 2 * hidden)``."""
        x_future = egocentric.future_dynamics(actions, features.DT)
        _, (h_last, _) = self.future_encoder(self._dynamics_in(x_future))
        return torch.cat([h_last[0], h_last[1]], -1)

    # ------------------------------------------------------------------------- training

    def _expand_classes(self, enc: Encoding) -> tuple[DecoderStart, torch.Tensor]:
        """Rows for every (sample, class) pair, class-minor: ``R = B * K``."""
        k = self.config.num_maneuver_classes
        batch = enc.h0.shape[0]
        z = torch.eye(k, dtype=enc.h0.dtype, device=enc.h0.device).repeat(batch, 1)
        start = self.decoder.start(enc.h0.repeat_interleave(k, 0), z)
        return start, enc.prev_action.repeat_interleave(k, 0)

    def forward(self, inputs: RTV3Inputs, actions: torch.Tensor, valid: torch.Tensor, step: int
                ) -> tuple[torch.Tensor, dict[str, float]]:
        """Negative ELBO (Eq. ELBO, Trajectron++ form).

        ``loss = -E_q[sum_t log p(a_t|h_t,z)] + beta * max(KL(q||p), KL_MIN) - I_p``, with the expectation
        over q exact: every one of the K classes is decoded (low variance, and q also gets gradient from
        the likelihood, not only through the KL).

        Args:
            actions: ``(B, H, 6)`` future body twists a_0..a_{H-1} (SI). valid: ``(B, H)`` bool, False = padding.
            step: training step (drives the beta and logit-clip annealing).
        """
        c = self.config
        clip, beta = self.clip_and_beta(step)
        enc = self.encode(inputs, augment=self.training)
        batch, k = enc.h0.shape[0], c.num_maneuver_classes
        # Padded steps lie after the episode end: the robot stands still there.
        actions_seen = torch.where(valid[..., None], actions, 0.0)
        h_plus = self.encode_future(actions_seen)
        log_p = self.maneuver_prior(enc.h0, clip)  # p(z | h0)
        log_q = self.maneuver_posterior(torch.cat([enc.h0, h_plus], -1), clip)  # q(z | h_H)
        target = self._twist_in(actions)
        weight = valid.to(target.dtype)
        start, prev = self._expand_classes(enc)
        step_ll = self.decoder.log_likelihood(start, prev, target.repeat_interleave(k, 0), LOG_PROB_CLAMP,
                                              c.rotation_conditioning)
        seq_ll = (step_ll.view(batch, k, -1) * weight[:, None]).sum(-1)  # (B, K)
        expected_ll = (log_q.exp() * seq_ll).sum(-1)
        nll = -expected_ll.mean()
        kl = kl_categorical(log_q, log_p).mean()
        mi = mutual_information(log_p)
        loss = nll + beta * kl.clamp_min(KL_MIN) - MUTUAL_INFORMATION_WEIGHT * mi
        info = {
            "nll": float(nll.detach()),
            "kl": float(kl.detach()),
            "mutual_information": float(mi.detach()),
            "beta": beta,
            "z_logit_clip": clip,
            "nll_per_step": float(nll.detach()) / max(float(weight.sum(-1).mean()), 1.0),
        }
        return loss, info

    # ------------------------------------------------------------------------- inference

    def maneuver_log_prior(self, enc: Encoding, step: int) -> torch.Tensor:
        """``(B, K)`` log p(z | h0) with the logit clip of training step ``step``."""
        return self.maneuver_prior(enc.h0, self.clip_and_beta(step)[0])

    def most_likely(self, inputs: RTV3Inputs, steps: int, step: int) -> torch.Tensor:
        """Paper's ML setting: ``z = argmax p(z|h0)``, then the mode of every Gaussian: ``(B, steps, 6)`` SI."""
        enc = self.encode(inputs)
        z_index = self.maneuver_log_prior(enc, step).argmax(-1)
        z = torch.nn.functional.one_hot(z_index, self.config.num_maneuver_classes).to(enc.h0.dtype)
        actions = self.decoder.rollout_mode(self.decoder.start(enc.h0, z), enc.prev_action, steps)
        return self._twist_out(actions)

    def modes(self, inputs: RTV3Inputs, steps: int, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Most-likely trajectory of every class (Best-of-Mode): ``(B, K, steps, 6)`` SI and log p(z|h0) ``(B, K)``."""
        enc = self.encode(inputs)
        start, prev = self._expand_classes(enc)
        actions = self.decoder.rollout_mode(start, prev, steps)
        batch, k = enc.h0.shape[0], self.config.num_maneuver_classes
        return self._twist_out(actions).view(batch, k, steps, 6), self.maneuver_log_prior(enc, step)

    def step0_mixture(self, inputs: RTV3Inputs, step: int) -> TwistMixture:
        """Step-0 mixture for the posterior (paper Sec. V), unscaled (m/s, rad/s), current EE body frame."""
        enc = self.encode(inputs)
        batch, k = enc.h0.shape[0], self.config.num_maneuver_classes
        scale = TRANSLATION_SCALE
        start, prev = self._expand_classes(enc)
        h = self.decoder.step(start, prev, start.state)[0]  # h_0 for every (sample, class)
        z = start.z
        decoder = self.decoder
        if self.config.factorized_rotation:
            trans = decoder.translation(h, z).scaled(1.0 / scale)
            trans_mean, trans_cov = trans.mean, trans.covariance()

            def rotation_given_translation(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                lead = _check_translation(v, batch, k)
                n = math.prod(lead)  # translations per (sample, class), evaluated in one pass
                with torch.no_grad():
                    rot = decoder.rotation(h.repeat(n, 1) if n > 1 else h, z.repeat(n, 1) if n > 1 else z,
                                           v.reshape(n * batch * k, 3).to(h) * scale)
                    return rot.mean.view(*lead, batch, k, 3), rot.covariance().view(*lead, batch, k, 3, 3)
        else:
            joint = decoder.joint(h, z)
            unscale = torch.tensor([1.0 / scale] * 3 + [1.0] * 3, dtype=h.dtype, device=h.device)
            joint = JointGaussian(joint.mean * unscale, joint.scale_tril * unscale[:, None])
            trans_mean, _, trans_cov, _ = joint.split()

            def rotation_given_translation(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                lead = _check_translation(v, batch, k)
                with torch.no_grad():
                    omega, gamma = joint.rotation_given_translation(v.reshape(*lead, batch * k, 3).to(h))
                    return (omega.view(*lead, batch, k, 3),
                            gamma.expand(*lead, batch * k, 3, 3).reshape(*lead, batch, k, 3, 3))

        return TwistMixture(
            log_weights=self.maneuver_log_prior(enc, step),
            trans_mean=trans_mean.reshape(batch, k, 3),
            trans_cov=trans_cov.reshape(batch, k, 3, 3),
            rotation_given_translation=rotation_given_translation,
        )


def _check_translation(v: torch.Tensor, batch: int, k: int) -> tuple[int, ...]:
    """Validate ``v (..., B, K, 3)``; returns its leading shape ``...``."""
    if not isinstance(v, torch.Tensor) or v.ndim < 3 or tuple(v.shape[-3:]) != (batch, k, 3):
        got = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
        raise ValueError(f"rotation_given_translation expects v of shape (..., {batch}, {k}, 3), got {got}")
    if not bool(torch.isfinite(v).all()):
        raise ValueError("rotation_given_translation: v contains NaN or inf")
    return tuple(v.shape[:-3])


__all__ = ["RTV3Model", "Encoding"]
