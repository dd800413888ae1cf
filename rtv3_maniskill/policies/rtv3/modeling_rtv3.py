"""RT-V3 prior as a LeRobot policy: batch handling, history queue, LeRobot API.

The network itself is :class:`rtv3_maniskill.policies.rtv3.model.RTV3Model`.

Inference with single-step observations (``observation.state`` of shape ``(B, 27)``): each
call of :meth:`RTV3Policy.select_action`, :meth:`RTV3Policy.predict_action_chunk`,
:meth:`RTV3Policy.predict_step0_mixture` or :meth:`RTV3Policy.predict_modes` appends the
observation to a T-step history queue (filled with copies of the first observation, like
LeRobot's ACT/Diffusion queues). Call exactly one of them per control step, or pass
``update_history=False`` to query without advancing the history, or pass a full
``(B, T, 27)`` history, which leaves the queue alone. :meth:`RTV3Policy.reset` clears it.
"""

from __future__ import annotations

import logging
from collections import deque
from pathlib import Path

import torch
from huggingface_hub import ModelCard, ModelCardData
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor

from rtv3_maniskill import features as ft
from rtv3_maniskill.policies.rtv3.batch import (
    RTV3Inputs,
    read_actions,
    read_context,
    read_states,
    subsample_grasps,
)
from rtv3_maniskill.policies.rtv3.configuration_rtv3 import RTV3Config
from rtv3_maniskill.policies.rtv3.model import RTV3Model
from rtv3_maniskill.policies.rtv3.model_card import MODEL_CARD_TEMPLATE, training_dataset_repo_id
from rtv3_maniskill.policies.rtv3.training_cache import TrainingCache
from rtv3_maniskill.twist_mixture import TwistMixture


class RTV3Policy(PreTrainedPolicy):
    """Robot Trajectron V3 prior ``p(a_{0:H-1} | s_{-T+1:0})`` (CVAE, discrete maneuver class)."""

    config_class = RTV3Config
    name = "rtv3"

    def __init__(self, config: RTV3Config, dataset_stats: dict | None = None, dataset_meta=None, **kwargs):
        """``dataset_stats`` / ``dataset_meta`` are accepted for LeRobot's factory; the stats are unused
        (the model normalises egocentrically and by fixed scales), the metadata gives the model card
        the training dataset's repo id."""
        super().__init__(config)
        self.dataset_repo_id = training_dataset_repo_id(dataset_meta)
        """The training dataset's repo id, named by the saved model card (``None``: unknown)."""
        # The training cache: the dataset's actions / states, read on the first training batch that needs them.
        self._cache_source = dataset_meta
        self._training_cache: TrainingCache | None = None
        if not config.input_features:
            config.input_features = config.default_input_features()
        if not config.output_features:
            config.output_features = config.default_output_features()
        # N and M follow the dataset when it stores the context keys separately (the packed
        # environment_state cannot be split without them: set num_points / max_grasps then).
        # (``(N, 6)``, or flat ``(N * 6,)`` as datasets store it: features.rows_of.)
        if ft.POINT_CLOUD in config.input_features:
            config.num_points = ft.rows_of(ft.POINT_CLOUD, config.input_features[ft.POINT_CLOUD].shape)
        if ft.GRASPS in config.input_features:
            config.max_grasps = ft.rows_of(ft.GRASPS, config.input_features[ft.GRASPS].shape)
        config.validate_features()
        self.config = config
        self.model = RTV3Model(config)
        # Training step counter (drives beta / logit-clip annealing); saved with the weights.
        self.register_buffer("train_step", torch.zeros((), dtype=torch.long))
        self._warned_no_target = False
        if config.init_weights_from:
            self._load_initial_weights(config.init_weights_from)
            config.init_weights_from = None  # consumed: saved checkpoints load on their own
        self.reset()

    def _load_initial_weights(self, folder: str) -> None:
        """Fine-tuning start: weights (and the training-step counter) of another checkpoint folder.

        Parameters that checkpoint lacks keep their fresh initialisation; shapes must match.
        """
        from safetensors.torch import load_file

        path = Path(folder).expanduser() / "model.safetensors"
        if not path.is_file():
            raise FileNotFoundError(f"init_weights_from: no model.safetensors in {folder}")
        state = load_file(str(path))
        own = self.state_dict()
        wrong = [k for k, v in state.items() if k in own and own[k].shape != v.shape]
        if wrong:
            raise ValueError(f"init_weights_from: shapes differ from this config for {wrong[:5]}")
        missing, unexpected = self.load_state_dict(state, strict=False)
        if missing or unexpected:
            logging.warning("init_weights_from %s: %d parameters freshly initialised %s, %d ignored %s",
                            folder, len(missing), missing[:3], len(unexpected), unexpected[:3])

    # ------------------------------------------------------------------ LeRobot API

    def get_optim_params(self) -> list[dict]:
        return [{"params": [p for p in self.parameters() if p.requires_grad]}]

    def _ensure_eval(self) -> None:
        """Inference runs in eval mode. ``eval()`` walks every submodule (0.5-1 ms per call for this network),
        so it runs only when the policy is in training mode (``train()`` / ``eval()`` set the whole tree)."""
        if self.training:
            self.eval()

    def reset(self) -> None:
        """Forget the observation history and any queued actions (call at every episode start)."""
        self._history: deque[Tensor] = deque(maxlen=self.config.n_obs_steps)
        self._action_queue: deque[Tensor] = deque(maxlen=self.config.n_action_steps)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        """Training loss (negative ELBO) on a dataset batch.

        Batch: ``observation.state (B, T, 27)``, context keys with or without the time axis (only the last
        frame is read) or ``observation.environment_state``, ``action (B, H, 6)``, optional ``action_is_pad
        (B, H)`` (padded steps are left out of the likelihood) and ``target_grasp_index`` (enables the
        random grasp-subset augmentation in training mode; note that LeRobot's processor pipeline drops
        keys outside ``observation.*`` / ``action`` / ``*_is_pad``). ``observation.state_is_pad`` needs no
        handling: LeRobot pads the history with copies of the first frame, exactly what the inference
        queue does at an episode start.
        """
        inputs = self._training_inputs(batch)
        actions, valid = self._training_actions(batch, inputs.states.shape[0])
        if self.training and ft.TARGET_GRASP not in batch and not self._warned_no_target:
            self._warned_no_target = True
            logging.warning(
                "training batch without %r: no grasp-subset augmentation (a pre-processor loaded with "
                "lerobot-train --policy.path drops it; fine-tune with --policy.type=rtv3 "
                "--policy.init_weights_from=DIR instead)", ft.TARGET_GRASP)
        if self.training and ft.TARGET_GRASP in batch:
            inputs = RTV3Inputs(inputs.states, subsample_grasps(inputs.context, batch[ft.TARGET_GRASP]))
        loss, info = self.model(inputs, actions.to(inputs.states), valid.to(inputs.states.device), int(self.train_step))
        if self.training:
            self.train_step += 1
        info["loss"] = float(loss.detach())
        return loss, info

    @torch.inference_mode()
    def select_action(self, batch: dict[str, Tensor], update_history: bool = True, **kwargs) -> Tensor:
        """Most likely body twist ``(B, 6)`` [v (m/s), w (rad/s)] in the current EE frame.

        Runs the model every ``n_action_steps`` steps (default 1: closed loop) and queues the rest.
        ``update_history=False`` reads a single-step observation without appending it to the history.
        """
        self._ensure_eval()
        inputs = self._inference_inputs(batch, update_history)
        if len(self._action_queue) == 0:
            steps = self.config.n_action_steps
            actions = self.model.most_likely(inputs, steps, int(self.train_step))
            self._action_queue.extend(actions.transpose(0, 1))
        return self._action_queue.popleft()

    @torch.inference_mode()
    def predict_action_chunk(self, batch: dict[str, Tensor], update_history: bool = True, **kwargs) -> Tensor:
        """Most likely future twists ``(B, H, 6)`` (argmax z, then the mode of each Gaussian)."""
        self._ensure_eval()
        inputs = self._inference_inputs(batch, update_history)
        return self.model.most_likely(inputs, self.config.horizon, int(self.train_step))

    @torch.inference_mode()
    def predict_modes(self, batch: dict[str, Tensor], update_history: bool = True) -> tuple[Tensor, Tensor]:
        """Most likely trajectory per maneuver class ``(B, K, H, 6)`` and log p(z|h0) ``(B, K)`` (Best-of-Mode)."""
        self._ensure_eval()
        inputs = self._inference_inputs(batch, update_history)
        return self.model.modes(inputs, self.config.horizon, int(self.train_step))

    @torch.no_grad()
    def predict_step0_mixture(self, batch: dict[str, Tensor], update_history: bool = True) -> TwistMixture:
        """Step-0 Gaussian mixture over ``a_0`` for the posterior (paper Sec. V), m/s and rad/s, EE frame."""
        self._ensure_eval()
        inputs = self._inference_inputs(batch, update_history)
        return self.model.step0_mixture(inputs, int(self.train_step))

    # ------------------------------------------------------------------ inputs

    def _to_model(self, inputs: RTV3Inputs) -> RTV3Inputs:
        param = next(self.parameters())
        ctx = inputs.context
        cast = lambda t: t.to(device=param.device, dtype=param.dtype)  # noqa: E731
        return RTV3Inputs(
            cast(inputs.states),
            type(ctx)(cast(ctx.point_cloud), ctx.point_mask.to(param.device), cast(ctx.grasps),
                      ctx.grasp_mask.to(param.device)),
        )

    def training_cache(self) -> TrainingCache | None:
        """The in-memory copy of the training dataset's actions and states (``training_cache.py``), read
        once from the dataset LeRobot's factory handed the policy; ``None`` without one."""
        if self._training_cache is None and self._cache_source is not None:
            self._training_cache = TrainingCache.from_dataset_meta(self._cache_source)
            self._cache_source = None
        return self._training_cache

    def _cached_frames(self, batch: dict[str, Tensor], what: str) -> tuple[TrainingCache, Tensor]:
        cache = self.training_cache()
        if cache is None or "index" not in batch:
            raise ValueError(
                f"training batch holds single frames ({what}) but no windows: LeRobot loads one row per sample "
                f"and the policy cuts the windows from the dataset it was made with, by the batch's 'index' (make "
                f"the policy with make_policy(cfg, ds_meta=dataset.meta)); cache: "
                f"{'none' if cache is None else 'yes'}, 'index' in batch: {'index' in batch}"
            )
        return cache, batch["index"]

    def _training_actions(self, batch: dict[str, Tensor], batch_size: int) -> tuple[Tensor, Tensor]:
        """``(B, H, 6)`` future actions and validity: the batch's window, or cut from the training cache."""
        action = batch.get(ft.ACTION)
        if isinstance(action, Tensor) and action.ndim == 2 and action.shape[-1] == 6:
            cache, index = self._cached_frames(batch, f"'{ft.ACTION}' {tuple(action.shape)}")
            actions, pad = cache.action_windows(index, self.config.horizon)
            batch = {ft.ACTION: actions.to(action.device), f"{ft.ACTION}_is_pad": pad.to(action.device)}
        return read_actions(batch, batch_size, self.config.horizon)

    def _training_inputs(self, batch: dict[str, Tensor]) -> RTV3Inputs:
        states = read_states(batch)
        if states.ndim == 2 and "index" in batch:  # single frames: cut the history from the training cache
            cache, index = self._cached_frames(batch, f"'{ft.STATE}' {tuple(states.shape)}")
            states = read_states({ft.STATE: cache.state_windows(index, self.config.n_obs_steps).to(states.device)})
        if states.ndim != 3 or states.shape[1] != self.config.n_obs_steps:
            raise ValueError(
                f"'{ft.STATE}' has shape {tuple(states.shape)}; training needs the history "
                f"(B, {self.config.n_obs_steps}, {ft.STATE_DIM}): the dataset's '{ft.STATE_HISTORY}', or, for a "
                f"dataset without it, the training cache (a policy made with the dataset's metadata and batches "
                f"with LeRobot's 'index')"
            )
        context = read_context(batch, self.config.num_points, self.config.max_grasps)
        _check_batch(states.shape[0], context.batch_size)
        return self._to_model(RTV3Inputs(states, context))

    def _inference_inputs(self, batch: dict[str, Tensor], update_history: bool) -> RTV3Inputs:
        states = read_states(batch)
        context = read_context(batch, self.config.num_points, self.config.max_grasps)
        t = self.config.n_obs_steps
        if states.ndim == 3:
            if states.shape[1] != t:
                raise ValueError(f"'{ft.STATE}' history has {states.shape[1]} steps; the policy uses T={t}")
            window = states
        else:
            current = states if states.ndim == 2 else states[None]
            if self._history and self._history[-1].shape != current.shape:
                raise ValueError(
                    f"'{ft.STATE}' batch shape changed from {tuple(self._history[-1].shape)} to "
                    f"{tuple(current.shape)}; call policy.reset() between episodes"
                )
            frames = [*self._history, current]
            if update_history:
                self._history.append(current)
            frames = [frames[0]] * max(t - len(frames), 0) + frames[-t:]
            window = torch.stack(frames, 1)
        _check_batch(window.shape[0], context.batch_size)
        return self._to_model(RTV3Inputs(window, context))

    # ------------------------------------------------------------------ model card

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, **kwargs):
        """LeRobot's loader; the training dataset's repo id comes from the checkpoint folder."""
        policy = super().from_pretrained(pretrained_name_or_path, **kwargs)
        if policy.dataset_repo_id is None:
            policy.dataset_repo_id = training_dataset_repo_id(pretrained_dir=pretrained_name_or_path)
        return policy

    def generate_model_card(self, dataset_repo_id: str | None, model_type: str, license: str | None,
                            tags: list[str] | None) -> ModelCard:
        """Model card from the RT-V3 template (offline: no Hub validation call)."""
        card_data = ModelCardData(
            license=license or "apache-2.0",
            library_name="lerobot",
            pipeline_tag="robotics",
            tags=sorted(set(tags or []) | {"robotics", "lerobot", model_type, "shared-control", "rt-v3"}),
            model_name=model_type,
            datasets=dataset_repo_id,
        )
        c = self.config
        return ModelCard.from_template(
            card_data,
            template_str=MODEL_CARD_TEMPLATE,
            history=c.n_obs_steps,
            horizon=c.horizon,
            classes=c.num_maneuver_classes,
            grasp_encoder=c.use_grasp_encoder,
            point_encoder=c.use_point_encoder,
            factorized=c.factorized_rotation,
            num_points=c.num_points,
            max_grasps=c.max_grasps,
            train_steps=int(self.train_step),
            num_parameters=sum(p.numel() for p in self.parameters()),
        )

    def _save_pretrained(self, save_directory: Path) -> None:
        """``config.json`` + ``model.safetensors`` (LeRobot) and a ``README.md`` model card."""
        super()._save_pretrained(save_directory)
        card = self.generate_model_card(self.dataset_repo_id, self.config.type, self.config.license, self.config.tags)
        card.save(str(Path(save_directory) / "README.md"))


def _check_batch(state_batch: int, context_batch: int) -> None:
    if state_batch != context_batch:
        raise ValueError(
            f"'{ft.STATE}' has batch size {state_batch} but the scene context has {context_batch}"
        )
