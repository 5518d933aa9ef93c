"""The actor's side of an SB3 off-policy algorithm: the policy an actor (or an evaluation) acts with, built without
anything that trains it (:class:`Untrained` in SB3's ``optimizer_class`` hook), and the learner's ``actor``
weights loaded into it (:meth:`khgrl.learner.sb3_offpolicy.SB3OffPolicy.actor_policy` builds it).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["SB3ActorPolicy", "Untrained"]


class Untrained:
    """The optimizer of a policy that acts and is never trained here (an actor's, an evaluation's), given to SB3's
    ``optimizer_class`` hook: a policy builds one for its actor and critics, and torch's first optimizer imports
    ``torch._dynamo`` (about 4 CPU-s at every actor's start). It holds nothing and refuses to step.

    :param params: the parameters an optimizer would train (not kept)
    """

    def __init__(self, params: Any, **_: Any) -> None:
        self.param_groups: list = []

    def zero_grad(self, set_to_none: bool = True) -> None:
        raise RuntimeError("an actor's policy is not trained: the learner trains")

    step = zero_grad

    def state_dict(self) -> dict:
        return {}


class SB3ActorPolicy:
    """An SB3 policy (evaluation mode) as an :class:`~khgrl.learner.algorithm.ActorPolicy`: actions from
    ``predict``, weights into its ``actor`` network.

    :param policy: an SB3 actor-critic policy with an ``actor`` network (SAC's, TQC's)
    """

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        policy.set_training_mode(False)

    def predict(self, obs: np.ndarray, deterministic: bool = False) -> tuple[np.ndarray, Any]:
        """SB3's ``predict`` (squashed into the action space's bounds).

        :param obs: one observation
        :param deterministic: the mean action (else a sample of the policy)
        """
        return self.policy.predict(obs, deterministic=deterministic)

    def weights_template(self) -> dict[str, tuple[int, ...]]:
        """The ``actor`` network's tensor names and shapes."""
        return {k: tuple(v.shape) for k, v in self.policy.actor.state_dict().items()}

    def load_weights(self, tensors: dict[str, Any]) -> None:
        """Load the learner's ``actor`` network.

        :param tensors: torch tensors by name
        """
        self.policy.actor.load_state_dict(tensors)
