"""The learner-algorithm interface: what the learner loop, checkpoints, resume, weights publishing, the actor's
policy and ``khgrl eval`` need of a reinforcement-learning algorithm, and the registry of those there are.

An algorithm is a class registered in :data:`REGISTRY` under the name ``--algo`` takes (``RunConfig.algo``,
recorded in the run's ``config.json``). The learner side (:class:`LearnerAlgorithm`) is built from the task's
spaces, the run's learner settings (``[tqc]``: :class:`~khgrl.common.config.settings.TQCSettings`) and a seed;
it stores batches in its :class:`~khgrl.learner.replay.StreamReplayBuffer`, trains n gradient steps at a time
on what a due iteration may sample, exports its policy network's weights for the actors, and saves and loads
itself together with its replay buffer in a checkpoint directory. It snapshots and restores its training state
and names what is not finite, so that the trainer rolls back an iteration that made the loss or parameters NaN
or infinite (:meth:`LearnerAlgorithm.snapshot`, :meth:`~LearnerAlgorithm.restore`,
:meth:`~LearnerAlgorithm.fault`). The actor side (:class:`ActorPolicy`) is only the policy network, on the CPU, in
float32, taking the learner's weights by name.

Implementations: ``tqc`` (:mod:`khgrl.learner.tqc`, sb3-contrib TQC, the paper's, the default), ``sac``
(:mod:`khgrl.learner.sac`), ``sac_ln`` (:mod:`khgrl.learner.sac_ln`, HIL-SERL's SAC), ``sac_cta``
(:mod:`khgrl.learner.sac_cta`, with HIL-SERL's update schedule); SB3-based ones share
:class:`khgrl.learner.sb3_offpolicy.SB3OffPolicy`. Adding one: a module with the class and one line in
:data:`REGISTRY`.
"""

from __future__ import annotations

from importlib import import_module
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

if TYPE_CHECKING:
    from khgrl.common.config.settings import TQCSettings
    from khgrl.learner.replay import StreamReplayBuffer

__all__ = ["LearnerAlgorithm", "ActorPolicy", "REGISTRY", "DEFAULT", "MODEL_FILE", "BUFFER_FILE", "algorithm_class",
           "check_algorithm"]

DEFAULT = "tqc"
MODEL_FILE = "model.zip"  # in a checkpoint directory: the networks, optimisers and training counters
BUFFER_FILE = "replay_buffer.pkl"  # and the replay buffer (our own file on local disk, never from the wire)

# name (--algo) -> "module:class", imported when asked for (so that naming one imports no learning library)
REGISTRY: dict[str, str] = {
    "tqc": "khgrl.learner.tqc:TQCAlgorithm",
    "sac": "khgrl.learner.sac:SACAlgorithm",
    "sac_ln": "khgrl.learner.sac_ln:SACLNAlgorithm",
    "sac_cta": "khgrl.learner.sac_cta:SACCTAAlgorithm",
}


class ActorPolicy(Protocol):
    """The policy network an actor runs (CPU, float32, evaluation mode) and ``khgrl eval`` evaluates."""

    def predict(self, obs: np.ndarray, deterministic: bool = False) -> tuple[np.ndarray, Any]:
        """The action for ``obs`` (SB3's ``predict``: in the action space's bounds), and a recurrent state (None)."""
        ...

    def weights_template(self) -> dict[str, tuple[int, ...]]:
        """The name and shape of every tensor :meth:`load_weights` takes (what a weights message must carry)."""
        ...

    def load_weights(self, tensors: dict[str, Any]) -> None:
        """Load the learner's weights (torch CPU float32 tensors by name, as :meth:`weights_template`)."""
        ...


class LearnerAlgorithm(Protocol):
    """The learner's side of an algorithm: one instance per learner incarnation."""

    name: ClassVar[str]
    gradient_steps: int  # per training iteration (the run's gradient_steps)
    logger: Any  # SB3's Logger (record / dump) the training scalars go to

    @classmethod
    def build(cls, task: Any, settings: TQCSettings, seed: int, device: str) -> LearnerAlgorithm:
        """A fresh algorithm on the task's spaces, seeded.

        :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: the passage world)
        :param settings: the run's learner settings
        :param seed: the seed of the networks (and of the minibatch sampling)
        :param device: the torch device to train on ('cpu', 'cuda')
        """
        ...

    @classmethod
    def load(cls, directory: Path, task: Any, settings: TQCSettings, device: str, *,
             buffer: StreamReplayBuffer | None = None) -> LearnerAlgorithm:
        """The algorithm and its replay buffer as :meth:`save` left them in ``directory``; with ``buffer``, the
        algorithm of a model checkpoint (:meth:`save` without the buffer) with that replay buffer."""
        ...

    @classmethod
    def actor_policy(cls, observation_space: Any, action_space: Any, settings: TQCSettings) -> ActorPolicy:
        """A fresh policy network for an actor (initialised from torch's global generator, as the caller seeded it)."""
        ...

    @classmethod
    def checkpoint_policy(cls, model_file: Path, observation_space: Any, action_space: Any,
                          settings: TQCSettings) -> ActorPolicy:
        """The policy held in a checkpoint's :data:`MODEL_FILE`; :class:`ValueError` (one line) if it does not load
        or does not fit these spaces and settings."""
        ...

    @property
    def buffer(self) -> StreamReplayBuffer:
        """The replay buffer (transitions, their flags and provenance; its ``lock`` and ``sample_limit``)."""
        ...

    def store(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray, done: np.ndarray,
              timeout: np.ndarray, *, intervened: np.ndarray, clipped: np.ndarray, actor: int, first_step: int,
              frames: dict[str, np.ndarray] | None = None, obs_frame: np.ndarray | None = None,
              next_frame: np.ndarray | None = None) -> None:
        """Store one batch of one actor's consecutive transitions (:meth:`StreamReplayBuffer.add_batch`); a camera
        task's with its frames in the wire's batch form (:mod:`khgrl.common.wire.frames`), ``obs``/``next_obs``
        its state vectors (:meth:`~khgrl.learner.frame_replay.FrameReplayBuffer.add_frames`)."""
        ...

    def train(self, gradient_steps: int, *, timestep: int, sample_limit: int | None) -> None:
        """Run ``gradient_steps`` gradient steps.

        :param gradient_steps: how many
        :param timestep: the environment step this iteration belongs to (SB3's ``num_timesteps``)
        :param sample_limit: sample only the first this many stored transitions (None: all)
        """
        ...

    def snapshot(self) -> Any:
        """A copy in memory of everything a training iteration changes (networks and target networks, optimiser
        states, entropy coefficient, update counter), for :meth:`restore`. Each snapshot is restored at most
        once (restoring may hand its tensors to the optimisers)."""
        ...

    def restore(self, snapshot: Any) -> None:
        """Put back what :meth:`snapshot` copied: the algorithm is as it was before the iteration.

        :param snapshot: what :meth:`snapshot` returned
        """
        ...

    def fault(self) -> str | None:
        """What is not finite after a training iteration (or in a loaded checkpoint): the first NaN or infinite
        training loss of the last iteration or parameter (networks, target networks, entropy coefficient),
        named; None when everything is finite."""
        ...

    def policy_weights(self) -> dict[str, np.ndarray]:
        """The actor's policy network: every tensor of :meth:`ActorPolicy.weights_template`, CPU float32 copies."""
        ...

    def set_logger(self, folder: Path, formats: tuple[str, ...]) -> None:
        """Write training scalars to ``folder`` in ``formats`` (SB3 logger: 'csv', 'tensorboard')."""
        ...

    def save(self, directory: Path, *, buffer: bool | StreamReplayBuffer = True) -> list[Path]:
        """Write :data:`MODEL_FILE` and (``buffer``) :data:`BUFFER_FILE` into ``directory`` (a buffer given: that
        one instead of the algorithm's); returns the files written."""
        ...


def check_algorithm(name: str) -> str:
    """``name`` if an algorithm is registered under it (nothing is imported).

    :param name: an ``--algo`` value
    :raises ValueError: no algorithm of that name (the message lists the registered ones)
    """
    if name not in REGISTRY:
        raise ValueError(f"unknown --algo {name!r}: registered are {', '.join(REGISTRY)}")
    return name


def algorithm_class(name: str) -> type[LearnerAlgorithm]:
    """The algorithm registered as ``name`` (its module imported now).

    :param name: an ``--algo`` value
    :raises ValueError: no algorithm of that name (the message lists the registered ones)
    """
    module, _, attr = REGISTRY[check_algorithm(name)].partition(":")
    return getattr(import_module(module), attr)
