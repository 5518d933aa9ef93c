"""``--algo sac_cta``: HIL-SERL's SAC (:mod:`khgrl.learner.sac_ln`: LayerNorm, tanh, 2 critics, temperature from
0.01, target entropy -|A|/2) with HIL-SERL's update schedule, the algorithm of ``--recipe hil-serl``
(:mod:`khgrl.common.config.hilserl`):

* **critic-to-actor ratio** (``[tqc] cta_ratio``): each gradient step is ``cta_ratio`` - 1 critic-only updates,
  then one update of the critics, the actor and the temperature, each on its own minibatch, the target critics
  Polyak-averaged after every critic update. Source: rail-berkeley/hil-serl@5d02aed
  examples/train_rlpd.py:317-338 ("run n-1 critic updates and 1 critic + actor update", each ``agent.update`` on
  a new batch), serl_launcher/serl_launcher/agents/continuous/sac.py:311-312 (the target update whenever the
  critic is updated), examples/experiments/config.py:10 (``cta_ratio: int = 2``);
* **backup entropy** (``[tqc] backup_entropy``): with it off the critics' target is r + gamma (1 - d) min Q'(s',
  a'), without SAC's - alpha log pi(a'|s'). Source: serl_launcher/serl_launcher/agents/continuous/sac.py:179-187,
  serl_launcher/serl_launcher/utils/launcher.py:85 (``backup_entropy=False``).

With ``cta_ratio`` 1 and ``backup_entropy`` on, a gradient step is SB3's SAC step exactly (the same random draws
in the same order: ``tests/unit/test_recipe_settings.py``). It is SB3's SAC with its ``train`` replaced (SB3's hook
for an off-policy algorithm's update); the rest -- buffer, checkpoints, the actors' policy -- is
:class:`~khgrl.learner.sb3_offpolicy.SB3OffPolicy`'s. It trains without CUDA graphs and without the compiled loss
(:mod:`khgrl.learner.cuda_graph` captures SB3's own step).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from khgrl.common.config.settings import TQCSettings
from khgrl.learner.sac_ln import SACLNAlgorithm
from stable_baselines3 import SAC
from stable_baselines3.common.utils import polyak_update
from torch.nn import functional as F

__all__ = ["CTASAC", "SACCTAAlgorithm"]


class CTASAC(SAC):
    """SB3's SAC with ``cta_ratio`` critic updates per actor update and the backup-entropy switch.

    :param args: SB3 SAC's positional arguments
    :param cta_ratio: critic updates per actor (and temperature) update, >= 1
    :param backup_entropy: subtract alpha log pi(a'|s') in the critics' target (SAC's); False: HIL-SERL's
    :param kwargs: SB3 SAC's keyword arguments
    """

    def __init__(self, *args: Any, cta_ratio: int = 1, backup_entropy: bool = True, **kwargs: Any) -> None:
        if int(cta_ratio) < 1:
            raise ValueError(f"cta_ratio must be >= 1, got {cta_ratio}")
        self.cta_ratio, self.backup_entropy = int(cta_ratio), bool(backup_entropy)
        super().__init__(*args, **kwargs)

    def _entropy(self, log_prob: th.Tensor | None) -> tuple[th.Tensor, th.Tensor | None]:
        """(alpha, its loss): the temperature as it is now, and -- given the actor's log-probabilities -- SAC's
        temperature loss (None when the coefficient is fixed or there is no log-probability)."""
        if self.ent_coef_optimizer is None or self.log_ent_coef is None:
            return self.ent_coef_tensor, None
        alpha = th.exp(self.log_ent_coef.detach())
        if log_prob is None:
            return alpha, None
        return alpha, -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()

    def _critic_update(self, data: Any, alpha: th.Tensor) -> float:
        """One critic update on ``data`` and the target critics' Polyak step; returns the critic loss."""
        with th.no_grad():
            next_actions, next_log_prob = self.actor.action_log_prob(data.next_observations)
            next_q = th.min(th.cat(self.critic_target(data.next_observations, next_actions), dim=1), dim=1,
                            keepdim=True)[0]
            if self.backup_entropy:
                next_q = next_q - alpha * next_log_prob.reshape(-1, 1)
            discounts = data.discounts if data.discounts is not None else self.gamma
            target = data.rewards + (1 - data.dones) * discounts * next_q
        loss = 0.5 * sum(F.mse_loss(q, target) for q in self.critic(data.observations, data.actions))
        self.critic.optimizer.zero_grad()
        loss.backward()
        self.critic.optimizer.step()
        polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
        return float(loss.item())

    def _full_update(self, batch_size: int, logs: dict[str, list[float]]) -> None:
        """The critic, actor and temperature update of a gradient step, in SB3's order (SAC.train's body)."""
        data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
        actions_pi, log_prob = self.actor.action_log_prob(data.observations)
        log_prob = log_prob.reshape(-1, 1)
        alpha, ent_loss = self._entropy(log_prob)
        logs["ent_coef"].append(float(alpha.item()))
        if ent_loss is not None:
            logs["ent_coef_loss"].append(float(ent_loss.item()))
            self.ent_coef_optimizer.zero_grad()
            ent_loss.backward()
            self.ent_coef_optimizer.step()
        logs["critic_loss"].append(self._critic_update(data, alpha))
        min_q_pi = th.min(th.cat(self.critic(data.observations, actions_pi), dim=1), dim=1, keepdim=True)[0]
        actor_loss = (alpha * log_prob - min_q_pi).mean()
        logs["actor_loss"].append(float(actor_loss.item()))
        self.actor.optimizer.zero_grad()
        actor_loss.backward()
        self.actor.optimizer.step()

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """``gradient_steps`` steps of ``cta_ratio`` - 1 critic updates and one full update (module docstring).

        :param gradient_steps: how many steps
        :param batch_size: the minibatch of each update
        """
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        logs: dict[str, list[float]] = {"ent_coef": [], "ent_coef_loss": [], "critic_loss": [], "actor_loss": []}
        for _ in range(gradient_steps):
            for _ in range(self.cta_ratio - 1):
                data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
                logs["critic_loss"].append(self._critic_update(data, self._entropy(None)[0]))
            self._full_update(batch_size, logs)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            if values:
                self.logger.record(f"train/{key}", float(np.mean(values)))


class SACCTAAlgorithm(SACLNAlgorithm):
    """HIL-SERL's SAC with its update schedule (the module docstring) through the learner-algorithm interface."""

    name = "sac_cta"

    @classmethod
    def sb3_class(cls) -> type:
        return CTASAC

    @classmethod
    def sb3_kwargs(cls, settings: TQCSettings, seed: int) -> dict[str, Any]:
        """:meth:`SACLNAlgorithm.sb3_kwargs` and the run's ``cta_ratio`` and ``backup_entropy``.

        :param settings: the run's learner settings
        :param seed: the model's seed
        """
        return {**super().sb3_kwargs(settings, seed), "cta_ratio": settings.cta_ratio,
                "backup_entropy": settings.backup_entropy}

    @staticmethod
    def graphs_on(settings: TQCSettings, device: str) -> bool:
        """Never: the CUDA graphs capture SB3's own step, not this one."""
        return False

    @staticmethod
    def compiled_on(settings: TQCSettings, device: str) -> bool:
        """Never: the compiled loss is TQC's."""
        return False
