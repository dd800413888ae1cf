"""Training the RT-V3 model from a compact cache, with PyTorch alone (no LeRobot, no ManiSkill).

This is the GPU recipe's training loop: a GPU machine that has PyTorch gets the repository and a
compact cache (``compact_cache.py``: the training set, the ``RTV3Config`` as LeRobot saved it, and
optional starting weights), trains, and writes checkpoints that ``RTV3Policy.from_pretrained``
loads (``config.json`` + ``model.safetensors``, the policy's parameter names). The step is
``lerobot-train``'s for this policy: the same batch (LeRobot's windows, grasp-subset augmentation
with the target kept), ``RTV3Model.forward`` (the negative ELBO), Adam with the config's learning
rate, weight decay and gradient clipping, and its exponential learning-rate decay. Frames are drawn
in shuffled epochs, as LeRobot's data loader does. ``lerobot-train --policy.type=rtv3`` stays the
default and tested way to train; this loop exists for machines where data loading through
LeRobot is not available or would be the bottleneck.

Checkpoints every ``save_freq`` steps under ``OUTPUT/checkpoints/NNNNNN/`` (and ``last``), each with
a ``training_state.pt`` (optimizer, scheduler, step, random state) that the next run with the same
output resumes from.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from rtv3_maniskill.policies.rtv3.batch import subsample_grasps
from rtv3_maniskill.policies.rtv3.compact_cache import (
    CACHE_FILE,
    CONFIG_FILE,
    INIT_WEIGHTS_FILE,
    CompactCache,
    WindowedCache,
)
from rtv3_maniskill.policies.rtv3.model import RTV3Model
from rtv3_maniskill.policies.rtv3.schedules import exponential_lr_factor

MODEL_PREFIX = "model."
"""``RTV3Policy`` holds the network as ``self.model``: its parameters are saved under this prefix."""
STEP_KEY = "train_step"
"""``RTV3Policy``'s training-step buffer (drives the KL / logit-clip annealing)."""
ADAM_BETAS, ADAM_EPS = (0.9, 0.999), 1e-8
"""LeRobot's ``AdamConfig`` defaults, which ``RTV3Config.get_optimizer_preset`` (``RTV3AdamConfig``) keeps."""


@dataclass
class TrainResult:
    """What one run did. ``samples_per_s``: training samples per second of wall clock, median over the
    logging intervals after the first (which holds start-up and, on a GPU, kernel compilation)."""

    steps: int
    final_step: int
    last_loss: float
    samples_per_s: float
    checkpoint: Path


def build_optimizer(model: RTV3Model, cfg: dict) -> torch.optim.Adam:
    """``RTV3AdamConfig``'s optimizer (LeRobot's Adam defaults, fused) with the config's lr and weight decay."""
    return torch.optim.Adam(model.parameters(), lr=cfg["optimizer_lr"], betas=ADAM_BETAS, eps=ADAM_EPS,
                            weight_decay=cfg["optimizer_weight_decay"], fused=True)


def training_step(model: RTV3Model, optimizer: torch.optim.Optimizer, windowed: WindowedCache, frames: torch.Tensor,
                  cfg: dict, model_step: int, device: str | torch.device) -> torch.Tensor:
    """One update on the cache's ``frames (B,)``, as ``lerobot-train`` makes it for this policy: the batch,
    the grasp-subset augmentation (target kept), the negative ELBO at annealing step ``model_step``,
    backward, gradient clipping, the optimizer step. Returns the loss (not synchronised)."""
    inputs, actions, valid, target = windowed.batch(frames, cfg["horizon"], device)
    inputs = type(inputs)(inputs.states, subsample_grasps(inputs.context, target))
    loss, _ = model(inputs, actions, valid, model_step)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg["optimizer_grad_clip_norm"], error_if_nonfinite=False)
    optimizer.step()
    return loss


def config_fields(cache_dir: Path) -> dict:
    """The saved ``RTV3Config`` as a plain dict (LeRobot's ``config.json``)."""
    path = cache_dir / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no {CONFIG_FILE} in {cache_dir}: not a compact training cache folder")
    cfg = json.loads(path.read_text())
    if cfg.get("type") != "rtv3":
        raise ValueError(f"{path} is a config of policy type {cfg.get('type')!r}, not 'rtv3'")
    return cfg


def model_state(model: RTV3Model, step: int) -> dict[str, torch.Tensor]:
    """The model's weights under ``RTV3Policy``'s parameter names (what ``save_pretrained`` writes)."""
    state = {MODEL_PREFIX + k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    state[STEP_KEY] = torch.tensor(step, dtype=torch.long)
    return state


def load_model_state(model: RTV3Model, path: Path) -> int:
    """Load ``RTV3Policy`` weights from ``path`` into ``model``; returns their training step."""
    state = load_file(str(path))
    own = {k[len(MODEL_PREFIX):]: v for k, v in state.items() if k.startswith(MODEL_PREFIX)}
    model.load_state_dict(own, strict=True)
    return int(state[STEP_KEY]) if STEP_KEY in state else 0


def _save_checkpoint(folder: Path, cfg: dict, model: RTV3Model, model_step: int, run_step: int, optimizer, scheduler,
                     epoch_state) -> None:
    """``model_step``: the weights' training step (annealing; a fine-tune counts on from its start);
    ``run_step``: the steps of this run, which a resumed run starts from."""
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    (tmp / CONFIG_FILE).write_text(json.dumps(cfg, indent=4))
    save_file(model_state(model, model_step), str(tmp / "model.safetensors"))
    torch.save({"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "step": run_step,
                "epoch_state": epoch_state, "torch_rng": torch.get_rng_state(),
                "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None},
               tmp / "training_state.pt")
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)  # a checkpoint is complete or absent


def train(cache_dir: str | Path, output_dir: str | Path, steps: int, batch_size: int = 64,
          device: str = "cpu", save_freq: int = 1000, log_freq: int = 50, seed: int = 0,
          lr: float | None = None, lr_decay: float | None = None, min_lr: float | None = None,
          time_limit_s: float | None = None, progress: bool = True) -> TrainResult:
    """Train ``steps`` steps (in all, counting the steps of a run this one resumes) from ``cache_dir``.

    Args:
        cache_dir: folder with ``cache.npz``, ``config.json`` and optionally ``init_model.safetensors``.
        output_dir: checkpoints go to ``output_dir/checkpoints``; an existing ``last`` is resumed.
        lr / lr_decay / min_lr: override the config's ``optimizer_lr`` / ``optimizer_lr_decay`` /
            ``optimizer_min_lr`` (written into the saved config).
        time_limit_s: stop (with a checkpoint) once this much wall clock has passed, even before ``steps``:
            a lent machine's lease ends; rerun to go on.
    """
    if steps <= 0 or batch_size <= 0 or save_freq <= 0 or log_freq <= 0:
        raise ValueError(f"steps, batch_size, save_freq and log_freq must be positive, got {steps}, {batch_size}, "
                         f"{save_freq}, {log_freq}")
    cache_dir, output_dir = Path(cache_dir), Path(output_dir)
    cfg = config_fields(cache_dir)
    for key, value in (("optimizer_lr", lr), ("optimizer_lr_decay", lr_decay), ("optimizer_min_lr", min_lr)):
        if value is not None:
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{key} must be a positive number, got {value}")
            cfg[key] = value
    compact = CompactCache.load(cache_dir / CACHE_FILE)
    if compact.history_steps != cfg["n_obs_steps"]:
        raise ValueError(f"the cache holds histories of T={compact.history_steps} steps, the config n_obs_steps="
                         f"{cfg['n_obs_steps']}")
    if (compact.point_cloud.shape[1], compact.grasps.shape[1]) != (cfg["num_points"], cfg["max_grasps"]):
        raise ValueError(f"the cache holds {compact.point_cloud.shape[1]} points / {compact.grasps.shape[1]} grasps "
                         f"per scene, the config num_points={cfg['num_points']} / max_grasps={cfg['max_grasps']}")
    windowed = compact.windows()
    windowed.contexts_to(device)
    if torch.device(device).type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    torch.manual_seed(seed)
    model = RTV3Model(SimpleNamespace(**cfg)).to(device)
    optimizer = build_optimizer(model, cfg)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, exponential_lr_factor(
        cfg["optimizer_lr_decay"], cfg["optimizer_min_lr"] / cfg["optimizer_lr"]))
    last = output_dir / "checkpoints" / "last"
    rng = np.random.default_rng(seed)
    epoch_state = {"order": rng.permutation(compact.num_frames).tolist(), "position": 0}
    done = 0
    if (last / "training_state.pt").is_file():
        state = torch.load(last / "training_state.pt", weights_only=False)
        model_step = load_model_state(model, last / "model.safetensors")
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        epoch_state, done = state["epoch_state"], int(state["step"])
        torch.set_rng_state(state["torch_rng"])
        if state["cuda_rng"] is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda_rng"])
        logging.info("resuming %s at step %d", last, done)
    else:
        model_step = load_model_state(model, cache_dir / INIT_WEIGHTS_FILE) if (
            cache_dir / INIT_WEIGHTS_FILE).is_file() else 0
    model_step -= done  # the model's annealing step = its starting step + the steps of this run
    if done >= steps:
        return TrainResult(0, done, float("nan"), float("nan"), last)
    rates, loss_value, tick, ticked = [], float("nan"), time.perf_counter(), done
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps, initial=done, desc="compact training", unit="step", mininterval=5.0)
    model.train()
    started = time.perf_counter()
    finished = done
    for step in range(done, steps):
        order, position = epoch_state["order"], epoch_state["position"]
        if position + batch_size > len(order):  # a new shuffled epoch (the last partial batch dropped)
            order, position = rng.permutation(compact.num_frames).tolist(), 0
        frames = torch.tensor(order[position:position + batch_size])
        epoch_state = {"order": order, "position": position + batch_size}
        loss = training_step(model, optimizer, windowed, frames, cfg, model_step + step, device)
        scheduler.step()
        finished = step + 1
        out_of_time = time_limit_s is not None and time.perf_counter() - started >= time_limit_s
        if finished % log_freq == 0 or finished == steps or out_of_time:
            loss_value = float(loss.detach())
            now = time.perf_counter()
            rates.append((finished - ticked) * batch_size / (now - tick))
            tick, ticked = now, finished
            if bar is not None:
                bar.set_postfix(loss=f"{loss_value:.3f}", samples_s=f"{rates[-1]:.0f}")
        if bar is not None:
            bar.update(1)
        if finished % save_freq == 0 or finished == steps or out_of_time:
            folder = output_dir / "checkpoints" / f"{finished:06d}"
            _save_checkpoint(folder, cfg, model, model_step + finished, finished, optimizer, scheduler, epoch_state)
            shutil.rmtree(last, ignore_errors=True)
            shutil.copytree(folder, last)
        if out_of_time:
            logging.info("time limit of %.0f s reached at step %d", time_limit_s, finished)
            break
    if bar is not None:
        bar.close()
    steady = rates[1:] or rates
    return TrainResult(finished - done, finished, loss_value, float(np.median(steady)), last)
