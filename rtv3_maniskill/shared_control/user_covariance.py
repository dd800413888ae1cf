"""The user-interface covariances ``S_u`` and ``G_u`` of the user twist likelihood (paper, Sec. V).

The posterior models a command as ``u ~ N(a, blockdiag(S_u, G_u))`` around the intended twist
``a``; :class:`UserCovarianceEstimator` adapts the two 3x3 blocks to the spread of the user's
recent commands, per batch element.
"""

from __future__ import annotations

import torch


class UserCovarianceEstimator:
    """Adaptive user-interface covariances ``S_u`` (translation) and ``G_u`` (rotation), per batch element.

    docs/PAPER_DETAILS.md: start ``diag([0.03]*3 + [0.1]*3)``; keep the last 14 non-zero commands;
    ``S <- 0.8 S + 0.2 sample-cov`` only while ``det^(1/3) > 0.01``. Our reading: the
    translation and rotation blocks are updated separately (the posterior only uses the
    two 3x3 blocks, and ``det^(1/3)`` is the geometric-mean variance of a 3x3 block); the
    sample covariance is over the stored commands (at least ``min_samples``); an update is
    applied only if the *updated* block keeps ``det^(1/3) > floor``, otherwise the block is
    left as it is. So the covariance follows the user's command spread but never
    collapses below a geometric-mean variance of ``floor`` (which would hand the user
    full authority), and it can grow again when the user becomes noisier.

    Args:
        batch_size: B.
        init_trans_var, init_rot_var: initial diagonal of ``S_u`` ((m/s)^2) and ``G_u`` ((rad/s)^2).
        window: the most recent active commands kept per element.
        decay: weight of the current block in an update (1 keeps the initial covariances).
        floor: least geometric-mean variance ``det^(1/3)`` of an updated block.
        min_samples: stored commands needed before the first update.
    """

    def __init__(
        self,
        batch_size: int = 1,
        init_trans_var: float = 0.03,
        init_rot_var: float = 0.1,
        window: int = 14,
        decay: float = 0.8,
        floor: float = 0.01,
        min_samples: int = 2,
    ) -> None:
        if batch_size < 1 or window < 2 or not 0.0 <= decay <= 1.0 or min_samples < 2 or min_samples > window:
            raise ValueError(
                f"bad UserCovarianceEstimator settings: batch_size={batch_size}, window={window}, "
                f"decay={decay}, min_samples={min_samples}"
            )
        if init_trans_var <= 0 or init_rot_var <= 0 or floor <= 0:
            raise ValueError("initial variances and floor must be positive")
        self.batch_size = batch_size
        self.init_trans_var = init_trans_var
        self.init_rot_var = init_rot_var
        self.window = window
        self.decay = decay
        self.floor = floor
        self.min_samples = min_samples
        self.reset()

    def reset(self) -> None:
        """Back to the initial diagonal covariances and an empty command buffer."""
        b = self.batch_size
        eye = torch.eye(3, dtype=torch.float64)
        self.trans_cov = (self.init_trans_var * eye).expand(b, 3, 3).clone()
        """``(B, 3, 3)`` S_u."""
        self.rot_cov = (self.init_rot_var * eye).expand(b, 3, 3).clone()
        """``(B, 3, 3)`` G_u."""
        self._buffer = torch.zeros(b, self.window, 6, dtype=torch.float64)
        self._count = torch.zeros(b, dtype=torch.long)

    @property
    def num_samples(self) -> torch.Tensor:
        """``(B,)`` commands currently stored."""
        return self._count.clamp(max=self.window)

    def update(self, user_twist: torch.Tensor, active: torch.Tensor) -> None:
        """Store the command ``(B, 6)`` of every element with ``active (B,)`` True and adapt."""
        if user_twist.shape != (self.batch_size, 6) or active.shape != (self.batch_size,):
            raise ValueError(
                f"expected user_twist ({self.batch_size}, 6) and active ({self.batch_size},), "
                f"got {tuple(user_twist.shape)} and {tuple(active.shape)}"
            )
        for i in torch.nonzero(active).flatten().tolist():
            self._buffer[i, self._count[i] % self.window] = user_twist[i].double()
            self._count[i] += 1
            n = int(min(self._count[i], self.window))
            if n < self.min_samples:
                continue
            samples = self._buffer[i, :n]
            centred = samples - samples.mean(0, keepdim=True)
            sample_cov = centred.T @ centred / (n - 1)
            for attr, block in (("trans_cov", slice(0, 3)), ("rot_cov", slice(3, 6))):
                current = getattr(self, attr)
                candidate = self.decay * current[i] + (1.0 - self.decay) * sample_cov[block, block]
                candidate = 0.5 * (candidate + candidate.T)
                det = torch.linalg.det(candidate)
                if det > 0 and float(det) ** (1.0 / 3.0) > self.floor:
                    current[i] = candidate
