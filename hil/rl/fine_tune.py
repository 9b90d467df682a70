"""What makes TRPO fine-tuning learn here, beside the release's method: steps whose action has no effect
left out of the update, and a critic fitted before the first policy update.

- `MaskedRolloutBuffer`: SB3's rollout buffer with a flag per step, whether the policy's action flew the
  vehicle (in `CrossGap-v0` the expert flies the traverse and ignores it). Returns and advantages are
  computed over every step as before (the expert's outcome reaches the policy's last steps through
  them); `get` yields only the flagged steps, so the surrogate, the KL and the critic's loss see no
  step whose action did nothing (they carried 40-66 % of a batch's squared normalised advantage).
- `FineTuneTRPO`: sb3-contrib's TRPO whose first updates fit the critic only: on each new batch the
  critic's explained variance is measured first (on returns it was not fitted on); below the target the
  batch trains the critic and the policy stays as it is, at or above it (or after ``critic_max_batches``)
  the policy updates begin. Its advantage estimates are then not mostly the critic's error.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import numpy as np
import torch
from sb3_contrib import TRPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.type_aliases import RolloutBufferSamples
from stable_baselines3.common.utils import explained_variance
from torch.nn import functional as F


class MaskedRolloutBuffer(RolloutBuffer):
    """A rollout buffer whose `get` yields only the steps marked as the policy's (`mark`)."""

    def reset(self) -> None:
        super().reset()
        self.active = np.ones((self.buffer_size, self.n_envs), dtype=bool)

    def mark(self, active: np.ndarray) -> None:
        """Flag the step about to be added (SB3 calls the callbacks' ``on_step`` before ``add``):
        ``active`` (n_envs,) whether each env's action flew its vehicle."""
        if self.pos < self.buffer_size:
            self.active[self.pos] = np.asarray(active, dtype=bool)

    def active_flat(self) -> np.ndarray:
        """The flags in the order `get` flattens the buffer (env by env)."""
        return self.active.swapaxes(0, 1).reshape(-1)

    def get(self, batch_size: int | None = None) -> Generator[RolloutBufferSamples, None, None]:
        assert self.full, "the buffer is not full"
        if not self.generator_ready:
            for name in ("observations", "actions", "values", "log_probs", "advantages", "returns"):
                self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])
            self.generator_ready = True
        keep = np.random.permutation(np.flatnonzero(self.active_flat()))
        size = len(keep) if batch_size is None else batch_size
        for start in range(0, len(keep), max(1, size)):
            yield self._get_samples(keep[start:start + size])


class FineTuneTRPO(TRPO):
    """TRPO with the critic fitted first (see the module doc). ``critic_target_ev``: None starts the
    policy updates at once (the release's method); ``critic_epochs``: passes over a batch when fitting
    the critic alone, in minibatches of ``critic_fit_batch`` (None: TRPO's ``batch_size``);
    ``critic_max_batches``: the most batches spent on the critic alone."""

    def __init__(self, *args: Any, critic_target_ev: float | None = None, critic_epochs: int = 20,
                 critic_max_batches: int = 20, critic_fit_batch: int | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.critic_fit_batch = critic_fit_batch
        self.critic_target_ev = critic_target_ev
        self.critic_epochs = critic_epochs
        self.critic_max_batches = critic_max_batches
        self.critic_batches = 0
        self.critic_ready = critic_target_ev is None
        self.critic_evs: list[float] = []  # each critic-only batch's explained variance, before fitting
        self.last_ev: float | None = None  # the last batch's, before its update

    def batch_explained_variance(self) -> float:
        """The critic's explained variance of the current batch's returns (its policy steps only), with
        the values it gave while the batch was collected."""
        buf = self.rollout_buffer
        active = buf.active if isinstance(buf, MaskedRolloutBuffer) else np.ones(buf.values.shape, bool)
        return float(explained_variance(buf.values[active].ravel(), buf.returns[active].ravel()))

    def fit_critic(self, epochs: int) -> float:
        """``epochs`` passes of minibatch regression of the critic on the batch's returns; the last loss."""
        loss = float("nan")
        for _ in range(epochs):
            for data in self.rollout_buffer.get(self.critic_fit_batch or self.batch_size):
                value_loss = F.mse_loss(data.returns, self.policy.predict_values(data.observations).flatten())
                self.policy.optimizer.zero_grad()
                value_loss.backward()
                for name, p in self.policy.named_parameters():
                    if "value" not in name:
                        p.grad = None  # the critic's parameters only
                self.policy.optimizer.step()
                loss = value_loss.item()
        return loss

    def train(self) -> None:
        self.last_ev = self.batch_explained_variance()
        if not self.critic_ready:
            self.critic_evs.append(self.last_ev)
            target = self.critic_target_ev if self.critic_target_ev is not None else -np.inf
            if self.last_ev < target and self.critic_batches < self.critic_max_batches:
                self.policy.set_training_mode(True)
                with torch.enable_grad():
                    self.fit_critic(self.critic_epochs)
                self.critic_batches += 1
                self.logger.record("train/critic_only_explained_variance", self.last_ev)
                return
            self.critic_ready = True
        super().train()
