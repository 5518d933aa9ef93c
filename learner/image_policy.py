"""SAC/TQC policies whose one image encoder (:class:`~khgrl.learner.image_encoder.ImageEncoder`) is shared by the
actor and the critics and trained by the critic loss alone, the actor reading its features detached -- DrQ's
scheme (Kostrikov et al. 2020; DrQ-v2, Yarats et al. 2021, ``obs.detach()`` in its actor update) -- and the
``policy``/``policy_kwargs`` that make an SB3 SAC, SAC-LN or sb3-contrib TQC model use it.

What SB3 does with ``share_features_extractor=True`` (stable-baselines3 2.9 ``SACPolicy._build``, sb3-contrib 2.9
``TQCPolicy._build``): the critic gets the actor's extractor object; the *actor's* optimiser holds all the actor's
parameters, the extractor's included, and the critic's optimiser all but the extractor's; the critics compute their
features under ``torch.set_grad_enabled(not share_features_extractor)`` (``ContinuousCritic.forward``, TQC's
``Critic.forward``), i.e. without autograd. So SB3 trains a shared extractor with the actor loss and never with the
critic loss: the opposite of DrQ. (Without sharing, SB3's default for SAC and TQC, actor and critics each train
their own extractor with their own loss: two encoders.)

:class:`DrQSharing` keeps SB3's sharing (one extractor object, in ``actor.features_extractor`` and
``critic.features_extractor``) and, after SB3's ``_build``:

* rebuilds the optimisers: the critic's holds all the critics' trainable parameters, the extractor's included;
  the actor's all the actor's but the extractor's;
* detaches the actor's features: a forward pre-hook on the actor's ``latent_pi`` (the first layer after the
  extractor in SB3's SAC and TQC actors) passes it ``features.detach()``;
* lets the critic compute its features with autograd for the critic loss and without it for the actor loss: a
  forward pre-hook on the critic sets its ``share_features_extractor`` flag (the one its ``forward`` reads) to
  whether the actions it is given require a gradient -- in SB3's ``train()`` the critic loss evaluates the replay
  buffer's actions, the actor loss the actor's reparametrised ones, so the actor loss's gradient reaches the
  actor's parameters through ``Q(s, pi(s))`` but not the encoder;
* puts the target critic's extractor (SB3 builds a separate one, Polyak-averaged with the critics) in training mode
  with the policy, so that the TD target's next observation is shifted as DrQ shifts it, with its own generator.

Hooks, not state: ``state_dict`` keys and SB3's ``save``/``load`` are SB3's own (``load`` builds the policy
again, hooks and optimisers included). Deviation from DrQ-v2: each pass of a batch through the encoder draws its
own shifts (SB3's ``train()`` encodes the observations three times and the next observations twice per step;
DrQ-v2 encodes each once).
"""

from __future__ import annotations

from typing import Any

import torch
from gymnasium import spaces
from khgrl.learner.image_encoder import DEFAULT_FEATURES, PAD, ImageEncoder, image_keys
from khgrl.learner.sac_ln import LayerNormSACPolicy
from sb3_contrib.tqc.policies import TQCPolicy
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

__all__ = ["DrQSharing", "DrQTQCPolicy", "DrQSACPolicy", "DrQLayerNormSACPolicy", "image_policy_kwargs",
           "tqc_image_policy", "sac_image_policy", "sac_ln_image_policy"]


def _detach_features(module: nn.Module, args: tuple[Any, ...]) -> tuple[Any, ...]:
    """Forward pre-hook of the actor's ``latent_pi``: its input (the extractor's features) detached."""
    return tuple(a.detach() for a in args)


def _features_grad_for_critic_loss(module: nn.Module, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
    """Forward pre-hook of the critic, called ``critic(obs, actions)``: features without autograd (SB3's
    ``share_features_extractor`` True) when the actions carry a gradient (the actor loss), with it otherwise."""
    actions = args[1] if len(args) > 1 else next(v for k, v in kwargs.items() if k.startswith("action"))
    module.share_features_extractor = bool(actions.requires_grad)


class DrQSharing:
    """Mixin before an SB3 SAC or TQC policy class: one features extractor for actor and critics, trained by the
    critic loss only, the actor's features detached (the module docstring).

    :param args: the policy class's positional arguments
    :param kwargs: its keyword arguments; ``share_features_extractor`` must be (and defaults to) True,
        ``normalize_images`` False (the extractor scales images itself)
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if not kwargs.setdefault("share_features_extractor", True):
            raise ValueError("a DrQ policy shares its features extractor (share_features_extractor=True)")
        if kwargs.setdefault("normalize_images", False):
            raise ValueError("a DrQ policy's extractor scales the images itself (normalize_images=False)")
        super().__init__(*args, **kwargs)

    def _build(self, lr_schedule: Any) -> None:
        """SB3's ``_build``, then the optimisers and hooks of the module docstring.

        :param lr_schedule: the learning-rate schedule
        """
        super()._build(lr_schedule)
        actor, critic = self.actor, self.critic
        encoder = actor.features_extractor
        if critic.features_extractor is not encoder:
            raise RuntimeError("SB3 did not share the features extractor")
        own = {id(p) for p in encoder.parameters()}
        self.actor.optimizer = self.optimizer_class([p for p in actor.parameters() if id(p) not in own],
                                                    lr=lr_schedule(1), **self.optimizer_kwargs)
        self.critic.optimizer = self.optimizer_class([p for p in critic.parameters() if p.requires_grad],
                                                     lr=lr_schedule(1), **self.optimizer_kwargs)
        actor.latent_pi.register_forward_pre_hook(_detach_features)
        critic.register_forward_pre_hook(_features_grad_for_critic_loss, with_kwargs=True)
        target = self.critic_target.features_extractor
        if isinstance(encoder, ImageEncoder) and isinstance(target, ImageEncoder):  # (its own shifts, reproducibly)
            target.shift.reseed(int(torch.randint(2 ** 62, (1,), generator=encoder.shift.generator)))

    def set_training_mode(self, mode: bool) -> None:
        """SB3's ``set_training_mode``, and the target critic's extractor in the same mode (its augmentation).

        :param mode: training mode
        """
        super().set_training_mode(mode)
        self.critic_target.features_extractor.train(mode)


class DrQTQCPolicy(DrQSharing, TQCPolicy):
    """sb3-contrib's TQC policy with DrQ's shared encoder (:class:`DrQSharing`)."""


class DrQSACPolicy(DrQSharing, SACPolicy):
    """Stable-Baselines3's SAC policy with DrQ's shared encoder (:class:`DrQSharing`)."""


class DrQLayerNormSACPolicy(DrQSharing, LayerNormSACPolicy):
    """SAC-LN's policy (HIL-SERL's networks, :mod:`khgrl.learner.sac_ln`) with DrQ's shared encoder."""


def image_policy_kwargs(observation_space: spaces.Dict, *, features_dim: int = DEFAULT_FEATURES,
                        frozen: bool = False, augment: bool = True, pad: int = PAD,
                        seed: int | None = None) -> dict[str, Any]:
    """The ``policy_kwargs`` of a DrQ policy for a Dict space of images and state vectors (merge with the run's,
    e.g. ``net_arch``).

    :param observation_space: the task's Dict observation space
    :param features_dim: each camera's feature size
    :param frozen: the trunks not trained (e.g. pretrained weights, :func:`~khgrl.learner.encoder_weights.
        load_encoder_weights`)
    :param augment: DrQ's random shift while training
    :param pad: its padding in pixels
    :param seed: its generator's seed (None: from torch's generator, which SB3 seeds)
    :raises ValueError: the space has no images, or a key that is neither image nor vector
    """
    image_keys(observation_space)
    return {"features_extractor_class": ImageEncoder,
            "features_extractor_kwargs": {"features_dim": features_dim, "frozen": frozen, "augment": augment,
                                          "pad": pad, "seed": seed},
            "share_features_extractor": True, "normalize_images": False}


def tqc_image_policy(observation_space: spaces.Dict, **encoder: Any) -> tuple[type, dict[str, Any]]:
    """The policy class and ``policy_kwargs`` of sb3-contrib TQC on this image space (``--algo tqc``).

    :param observation_space: the task's Dict observation space
    :param encoder: :func:`image_policy_kwargs`'s keyword arguments
    """
    return DrQTQCPolicy, image_policy_kwargs(observation_space, **encoder)


def sac_image_policy(observation_space: spaces.Dict, **encoder: Any) -> tuple[type, dict[str, Any]]:
    """The policy class and ``policy_kwargs`` of SB3's SAC on this image space (``--algo sac``).

    :param observation_space: the task's Dict observation space
    :param encoder: :func:`image_policy_kwargs`'s keyword arguments
    """
    return DrQSACPolicy, image_policy_kwargs(observation_space, **encoder)


def sac_ln_image_policy(observation_space: spaces.Dict, **encoder: Any) -> tuple[type, dict[str, Any]]:
    """The policy class and ``policy_kwargs`` of SAC-LN on this image space (``--algo sac_ln``, HIL-SERL's).

    :param observation_space: the task's Dict observation space
    :param encoder: :func:`image_policy_kwargs`'s keyword arguments
    """
    return DrQLayerNormSACPolicy, image_policy_kwargs(observation_space, **encoder)
