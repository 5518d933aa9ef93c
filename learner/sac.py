"""``--algo sac``: Stable-Baselines3's SAC (Haarnoja et al., "Soft Actor-Critic Algorithms and Applications")
through the learner-algorithm interface, as a second implementation beside TQC.

Where each setting comes from:

* from the run's learner settings (``[tqc]``, :class:`~khgrl.common.config.settings.TQCSettings`, the paper's
  TQC settings of Section IV), because they mean the same in SAC -- through the same
  :meth:`~khgrl.common.config.settings.TQCSettings.sb3_kwargs` TQC gets: ``learning_rate`` (1e-3, actor, critics
  and entropy coefficient), ``tau`` (0.02), ``gamma`` (0.99), ``train_freq`` (8) and ``gradient_steps`` (8),
  ``ent_coef`` ("auto": learned), ``policy_kwargs.net_arch`` (256, 256 for the actor and each critic),
  ``learning_starts`` (100), ``batch_size`` (256), ``buffer_size`` (200,000), ``device``, ``seed``;
* SB3 SAC's own defaults for what TQC has no counterpart of or sets differently: 2 Q-critics (``n_critics``)
  with the minimum as target instead of truncated quantiles, ``target_update_interval`` 1, ``target_entropy``
  "auto" (minus the action dimension), no gSDE;
* the learner's as for TQC: the replay buffer is a :class:`~khgrl.learner.replay.StreamReplayBuffer`, the actors
  get the policy's ``actor`` network (:class:`~khgrl.learner.sb3_offpolicy.SB3OffPolicy`).
"""

from __future__ import annotations

from khgrl.learner.sb3_offpolicy import SB3OffPolicy

__all__ = ["SACAlgorithm"]


class SACAlgorithm(SB3OffPolicy):
    """SB3's SAC through the learner-algorithm interface (:class:`~khgrl.learner.sb3_offpolicy.SB3OffPolicy`)."""

    name = "sac"

    @classmethod
    def sb3_class(cls) -> type:
        from stable_baselines3 import SAC

        return SAC

    @classmethod
    def policy_class(cls) -> type:
        from stable_baselines3.sac.policies import SACPolicy

        return SACPolicy
