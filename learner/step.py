"""One gradient step of Stable-Baselines3's SAC and sb3-contrib's TQC as a function of a minibatch: the body of
their ``train()`` loop (SB3 2.x ``SAC.train``, sb3-contrib 2.x ``TQC.train``), statement for statement on the
model's own networks, optimisers, entropy coefficient and ``polyak_update``, with the training scalars left on the
device instead of read with ``.item()`` after each loss. So it can be captured as one CUDA graph
(:mod:`khgrl.learner.cuda_graph`), and it leaves the same parameters as the library's ``train()`` from the same
minibatches and noise (tests/unit/test_graph_step.py: TQC, SAC and SAC-LN in float64 on the CPU).

The step, as SB3 does it (``alpha`` the entropy coefficient, ``H`` the target entropy):

1. ``a, log pi(a|s) = actor(s)`` (reparametrised, squashed Gaussian); ``alpha = exp(log_alpha)`` before its update;
2. entropy-coefficient loss ``-(log_alpha * (log pi + H)).mean()``, one Adam step (learned ``alpha`` only);
3. the target from the target critics at ``s'`` and ``a' ~ pi(s')``: SAC the minimum of the 2 Q-values, TQC the
   ``2 x 25`` quantiles sorted with the top ``2 x 2`` dropped; minus ``alpha log pi(a'|s')``, times
   ``gamma (1 - done)``, plus the reward;
4. critic loss (SAC: ``0.5`` times the sum of the critics' mean squared errors; TQC: the quantile Huber loss), one
   Adam step;
5. actor loss ``(alpha log pi(a|s) - Q(s, a)).mean()`` (SAC: the minimum over critics; TQC: the mean over critics
   and quantiles), one Adam step;
6. Polyak update of the target critics (every ``target_update_interval``-th step of an iteration).
"""

from __future__ import annotations

from typing import Any, NamedTuple

__all__ = ["Minibatch", "SB3Step", "SCALARS"]

# what one step returns, in this order (SB3 logs their means per iteration as train/<name>)
SCALARS = ("ent_coef", "actor_loss", "critic_loss", "ent_coef_loss")


class Minibatch(NamedTuple):
    """The five tensors of SB3's ``ReplayBufferSamples`` a step uses (rewards and dones of shape ``(B, 1)``)."""

    observations: Any
    actions: Any
    next_observations: Any
    dones: Any
    rewards: Any

    @classmethod
    def split(cls, rows: Any, obs_dim: int, act_dim: int) -> Minibatch:
        """Views into rows laid out as :meth:`~khgrl.learner.replay.StreamReplayBuffer.sample_into` writes them.

        :param rows: a ``(B, 2 * obs_dim + act_dim + 2)`` tensor
        :param obs_dim: observation size
        :param act_dim: action size
        """
        o, a = obs_dim, act_dim
        return cls(rows[:, :o], rows[:, o:o + a], rows[:, o + a:2 * o + a], rows[:, -2:-1], rows[:, -1:])


class SB3Step:
    """The gradient step of an SB3 SAC or sb3-contrib TQC model (the module docstring), on its own parameters.

    :param model: the SB3 model (``SAC`` or ``TQC``, any policy of theirs: SAC-LN's too)
    :param compile_loss: TQC's quantile Huber loss compiled by ``torch.compile`` (one fused kernel on the CPU
        instead of a dozen passes over the ``B x 2 x 25 x 46`` pairwise differences; it rounds differently, so the
        run opts in: ``--compile-loss``)
    """

    def __init__(self, model: Any, compile_loss: bool = False) -> None:
        from sb3_contrib.common.utils import quantile_huber_loss

        self.model = model
        self.quantiles = hasattr(model, "top_quantiles_to_drop_per_net")  # TQC (else SAC)
        if model.use_sde:
            raise ValueError("the step function does not support gSDE")
        self.huber = quantile_huber_loss
        if compile_loss and self.quantiles:
            import torch

            self.huber = torch.compile(quantile_huber_loss, dynamic=False)

    def __call__(self, batch: Minibatch, polyak: bool = True) -> Any:
        """One gradient step on ``batch``; returns the step's :data:`SCALARS` as one tensor on the model's device.

        :param batch: the minibatch
        :param polyak: update the target critics after it (SB3: when ``step % target_update_interval == 0``)
        """
        import torch as th
        from stable_baselines3.common.utils import polyak_update

        m = self.model
        actions_pi, log_prob = m.actor.action_log_prob(batch.observations)
        log_prob = log_prob.reshape(-1, 1)
        if m.ent_coef_optimizer is not None and m.log_ent_coef is not None:
            ent_coef = th.exp(m.log_ent_coef.detach())
            ent_coef_loss = -(m.log_ent_coef * (log_prob + m.target_entropy).detach()).mean()
            m.ent_coef_optimizer.zero_grad()
            ent_coef_loss.backward()
            m.ent_coef_optimizer.step()
        else:
            ent_coef = m.ent_coef_tensor
            ent_coef_loss = th.zeros((), device=log_prob.device, dtype=log_prob.dtype)
        with th.no_grad():
            next_actions, next_log_prob = m.actor.action_log_prob(batch.next_observations)
            target = self._target(batch, next_actions, next_log_prob, ent_coef)
        critic_loss = self._critic_loss(batch, target)
        m.critic.optimizer.zero_grad()
        critic_loss.backward()
        m.critic.optimizer.step()
        actor_loss = (ent_coef * log_prob - self._q_pi(batch, actions_pi)).mean()
        m.actor.optimizer.zero_grad()
        actor_loss.backward()
        m.actor.optimizer.step()
        if polyak:  # (SB3's polyak_update, its two operations on all tensors at once: the same numbers)
            with th.no_grad():
                targets = list(m.critic_target.parameters())
                th._foreach_mul_(targets, 1 - m.tau)
                th._foreach_add_(targets, list(m.critic.parameters()), alpha=m.tau)
            polyak_update(m.batch_norm_stats, m.batch_norm_stats_target, 1.0)
        return th.stack([ent_coef.detach().reshape(()).to(log_prob.dtype), actor_loss.detach(), critic_loss.detach(),
                         ent_coef_loss.detach()])

    def _target(self, batch: Minibatch, next_actions: Any, next_log_prob: Any, ent_coef: Any) -> Any:
        """Step 3: the critics' regression target (SAC: ``(B, 1)``; TQC: ``(B, 1, kept quantiles)``)."""
        import torch as th

        m = self.model
        if self.quantiles:
            next_quantiles = m.critic_target(batch.next_observations, next_actions)
            n_target = m.critic.quantiles_total - m.top_quantiles_to_drop_per_net * m.critic.n_critics
            next_quantiles, _ = th.sort(next_quantiles.reshape(next_quantiles.shape[0], -1))
            next_quantiles = next_quantiles[:, :n_target]
            target = next_quantiles - ent_coef * next_log_prob.reshape(-1, 1)
            target = batch.rewards + (1 - batch.dones) * m.gamma * target
            return target.unsqueeze_(dim=1)
        next_q = th.cat(m.critic_target(batch.next_observations, next_actions), dim=1)
        next_q, _ = th.min(next_q, dim=1, keepdim=True)
        next_q = next_q - ent_coef * next_log_prob.reshape(-1, 1)
        return batch.rewards + (1 - batch.dones) * m.gamma * next_q

    def _critic_loss(self, batch: Minibatch, target: Any) -> Any:
        """Step 4's loss: TQC's quantile Huber loss, or SAC's halved sum of mean squared errors."""
        import torch.nn.functional as F  # noqa: N812 - SB3's name

        m = self.model
        current = m.critic(batch.observations, batch.actions)
        if self.quantiles:
            return self.huber(current, target, sum_over_quantiles=False)
        return 0.5 * sum(F.mse_loss(current_q, target) for current_q in current)

    def _q_pi(self, batch: Minibatch, actions_pi: Any) -> Any:
        """Step 5's value of the policy's actions: TQC's mean over critics and quantiles, SAC's minimum."""
        import torch as th

        m = self.model
        if self.quantiles:
            return m.critic(batch.observations, actions_pi).mean(dim=2).mean(dim=1, keepdim=True)
        q_values_pi = th.cat(m.critic(batch.observations, actions_pi), dim=1)
        return th.min(q_values_pi, dim=1, keepdim=True)[0]
