"""``--algo sac_ln``: the SAC of HIL-SERL (Luo et al. 2024, "Precise and Dexterous Robotic Manipulation via
Human-in-the-Loop Reinforcement Learning") in Stable-Baselines3: SB3's SAC whose actor and critic networks have a
LayerNorm after each hidden Linear layer and tanh activations. ``--method hil-serl`` implies it, together with
RLPD's symmetric sampling (``[tqc] sampling rlpd``, :mod:`khgrl.learner.replay`).

Sources: HIL-SERL's code, rail-berkeley/hil-serl@5d02aed700202c34d120224ae2c8da6795223b0e (``HS`` below; its agent
is ``make_sac_pixel_agent``, the only SAC agent its launcher makes; paths under ``serl_launcher/serl_launcher/``
unless they start with ``examples/``), and RLPD's, ikostrikov/rlpd@c90fd4baf28c9c9ef40a81460a2e395092844f88.

Taken from HIL-SERL:

* LayerNorm after each hidden Linear, before the activation, in the critics and the actor:
  HS:utils/launcher.py:75 and :80 (``use_layer_norm``), the order Dense -> LayerNorm -> activation
  HS:networks/mlp.py:24-31; RLPD's critics have it too (rlpd@c90fd4b:configs/rlpd_config.py:9
  ``critic_layer_norm``). Here: SB3's ``create_mlp(..., post_linear_modules=[nn.LayerNorm])``;
* tanh hidden activations in the critics and the actor: HS:utils/launcher.py:74 and :79 (``nn.tanh``);
* 2 critics, the target the minimum over both: HS:utils/launcher.py:86-87 (``critic_ensemble_size=2``,
  ``critic_subsample_size=None``), HS:agents/continuous/sac.py:165-176 -- SB3 SAC's ``n_critics`` 2. RLPD uses
  10 critics with the minimum over a random 2 (rlpd@c90fd4b:configs/rlpd_config.py:7-8); we take HIL-SERL's 2;
* initial entropy temperature 0.01, learned: HS:utils/launcher.py:83 (``temperature_init=1e-2``) -- SB3's
  ``ent_coef="auto_0.01"`` (a run that sets ``[tqc] ent_coef`` to anything but ``auto`` keeps its value);
* target entropy -|A|/2: HS:agents/continuous/sac.py:414-415 (``target_entropy = -actions.shape[-1] / 2``, the
  launcher passes None, HS:utils/launcher.py:57) -- SB3's ``target_entropy``;
* batch 256, replay capacity 200,000, 100 transitions before training: HS:examples/experiments/config.py:9, :14,
  :17 -- the same as the run's ``[tqc]`` ``batch_size``, ``buffer_size``, ``learning_starts``.

From the run's learner settings (``[tqc]``, :class:`~khgrl.common.config.settings.TQCSettings`, the paper's TQC
settings) like ``--algo tqc`` and ``sac``, so that all methods of the comparison share sizes and update-to-data
ratio: ``learning_rate``, ``tau``, ``gamma``, ``train_freq`` and ``gradient_steps`` (the UTD), ``batch_size``,
``buffer_size``, ``learning_starts``, ``net_arch`` (256, 256: HIL-SERL's too, HS:utils/launcher.py:76, :81).

Where this deviates from HIL-SERL, and why:

* learning rate 1e-3 (HIL-SERL: 3e-4 for actor, critics and temperature, HS:agents/continuous/sac.py:358-366),
  tau 0.02 (HIL-SERL: 0.005, sac.py:369), gamma 0.99 (HIL-SERL: 0.97, HS:examples/experiments/config.py:11):
  the run's settings, the same for every method compared;
* one critic update per actor update, both every gradient step (SB3's SAC), where HIL-SERL updates the critics
  ``cta_ratio`` = 2 times per actor update (HS:examples/experiments/config.py:10,
  HS:examples/train_rlpd.py:317-338): the same gradient steps and UTD as the other methods;
* the entropy term in the critic's target (SB3's SAC; HIL-SERL: ``backup_entropy=False``,
  HS:utils/launcher.py:85), and the actor's objective on the minimum of the two critics (SB3; HIL-SERL: their
  mean, HS:agents/continuous/sac.py:224): SB3's SAC as is, no private training loop;
* the policy's log-std clipped to SB3's [-20, 2] (HIL-SERL: std in [1e-5, 5], HS:utils/launcher.py:68-72); SB3's
  (PyTorch's) weight initialisation; no image encoder (the tasks here have state observations).

The actors get the policy's ``actor`` network (with its LayerNorm parameters); an actor builds
:class:`LayerNormSACPolicy` on the CPU (:meth:`~khgrl.learner.sb3_offpolicy.SB3OffPolicy.actor_policy`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from khgrl.common.config.settings import TQCSettings
from khgrl.learner.sac import SACAlgorithm
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, create_mlp
from stable_baselines3.sac.policies import Actor, SACPolicy
from torch import nn

__all__ = ["SACLNAlgorithm", "LayerNormSACPolicy", "LayerNormActor", "LayerNormCritic", "INITIAL_ENT_COEF"]

INITIAL_ENT_COEF = 0.01  # HIL-SERL's temperature_init (the module docstring)
NORM = [nn.LayerNorm]  # after each hidden Linear (create_mlp's post_linear_modules)


class LayerNormCritic(ContinuousCritic):
    """SB3's SAC critics (``n_critics`` Q-networks) with a LayerNorm after each hidden Linear layer.

    :param observation_space: the observation space
    :param action_space: the action space
    :param net_arch: hidden layer sizes
    :param features_extractor: the features extractor (a Flatten for vector observations)
    :param features_dim: its output size
    :param activation_fn: the hidden activation
    :param normalize_images: SB3's image normalisation (unused for vectors)
    :param n_critics: how many Q-networks
    :param share_features_extractor: whether the actor's features extractor is shared
    """

    def __init__(self, observation_space: Any, action_space: Any, net_arch: list[int],
                 features_extractor: BaseFeaturesExtractor, features_dim: int,
                 activation_fn: type[nn.Module] = nn.Tanh, normalize_images: bool = True, n_critics: int = 2,
                 share_features_extractor: bool = True) -> None:
        super().__init__(observation_space, action_space, net_arch, features_extractor, features_dim, activation_fn,
                         normalize_images, n_critics=0, share_features_extractor=share_features_extractor)
        self.n_critics = n_critics  # (SB3 made none: they are made here, with the LayerNorms, in SB3's order)
        action_dim = get_action_dim(self.action_space)
        for idx in range(n_critics):
            q_net = nn.Sequential(*create_mlp(features_dim + action_dim, 1, net_arch, activation_fn,
                                              post_linear_modules=NORM))
            self.add_module(f"qf{idx}", q_net)
            self.q_networks.append(q_net)


class LayerNormActor(Actor):
    """SB3's SAC actor whose hidden layers (``latent_pi``) have a LayerNorm after each Linear layer (SB3's
    arguments; see :class:`stable_baselines3.sac.policies.Actor`).

    :param args: SB3's Actor positional arguments
    :param kwargs: SB3's Actor keyword arguments (gSDE is not supported)
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.use_sde:
            raise ValueError("sac_ln has no gSDE actor")
        self.latent_pi = nn.Sequential(*create_mlp(self.features_dim, -1, self.net_arch, self.activation_fn,
                                                   post_linear_modules=NORM))


class LayerNormSACPolicy(SACPolicy):
    """SB3's SAC policy with :class:`LayerNormActor` and :class:`LayerNormCritic`, tanh activations by default (the
    module docstring). SB3 builds it from its policy hooks (``make_actor``, ``make_critic``).

    :param args: SB3's SACPolicy positional arguments (observation space, action space, learning-rate schedule)
    :param activation_fn: the hidden activation of actor and critics (HIL-SERL's tanh)
    :param kwargs: SB3's SACPolicy keyword arguments (``net_arch``, ``n_critics``, ...)
    """

    def __init__(self, *args: Any, activation_fn: type[nn.Module] = nn.Tanh, **kwargs: Any) -> None:
        super().__init__(*args, activation_fn=activation_fn, **kwargs)

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> LayerNormActor:
        """The actor (SB3's hook), with LayerNorms.

        :param features_extractor: a features extractor to use (None: a new one)
        """
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return LayerNormActor(**actor_kwargs).to(self.device)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> LayerNormCritic:
        """The critics (SB3's hook), with LayerNorms.

        :param features_extractor: a features extractor to use (None: a new one)
        """
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return LayerNormCritic(**critic_kwargs).to(self.device)


class SACLNAlgorithm(SACAlgorithm):
    """HIL-SERL's SAC (the module docstring) through the learner-algorithm interface
    (:class:`~khgrl.learner.sb3_offpolicy.SB3OffPolicy`)."""

    name = "sac_ln"

    @classmethod
    def policy_class(cls) -> type:
        return LayerNormSACPolicy

    @classmethod
    def sb3_kwargs(cls, settings: TQCSettings, seed: int) -> dict[str, Any]:
        """The run's settings (:meth:`TQCSettings.sb3_kwargs`), the entropy coefficient learned from 0.01 (unless
        the run sets one other than ``auto``).

        :param settings: the run's learner settings
        :param seed: the model's seed
        """
        kwargs = settings.sb3_kwargs(seed)
        if kwargs["ent_coef"] == "auto":
            kwargs["ent_coef"] = f"auto_{INITIAL_ENT_COEF}"
        return kwargs

    @classmethod
    def space_kwargs(cls, action_space: Any) -> dict[str, Any]:
        """The target entropy: minus half the action dimension (HIL-SERL).

        :param action_space: the task's action space
        """
        return {"target_entropy": -float(np.prod(action_space.shape)) / 2}
