"""Training schedules of the RT-V3 prior that need neither LeRobot nor the model."""

from __future__ import annotations

from collections.abc import Callable


def exponential_lr_factor(decay_rate: float, min_ratio: float) -> Callable[[int], float]:
    """Per-step learning-rate factor ``max(decay_rate**step, min_ratio)`` (Trajectron++'s exponential decay),
    for ``torch.optim.lr_scheduler.LambdaLR``."""
    return lambda step: max(decay_rate**step, min_ratio)
