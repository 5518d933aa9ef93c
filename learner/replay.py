"""The learner's replay buffer: SB3's :class:`ReplayBuffer` plus what the learner knows about each slot.

Besides SB3's arrays, every slot records whether the human intervened on that transition (the stored action
is then the human's a_h), whether the action was clipped by the safety layer, and its provenance: the actor
stream it came from (a code into the learner's stream table, ``-1`` for an empty slot) and the transition's
running index in that actor's stream. :meth:`StreamReplayBuffer.add` writes them in the same slot as SB3's
fields, so they can never drift apart, and they travel inside the buffer: TQC builds this class through
``replay_buffer_class`` and ``save_replay_buffer``/``load_replay_buffer`` save and load them with the rest.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer

__all__ = ["StreamReplayBuffer", "SIDE_ARRAYS"]

# name of each per-slot array as exported by :meth:`StreamReplayBuffer.side_arrays` (and load_checkpoint_arrays)
SIDE_ARRAYS = ("provenance_actor", "provenance_step", "intervened", "clipped")


class StreamReplayBuffer(ReplayBuffer):
    """A replay buffer for one environment (``n_envs=1``) whose slots also hold the intervention and clip flags
    and the provenance (actor code, the actor's transition index) of the transition stored there.

    Constructed by SB3 (``TQC(..., replay_buffer_class=StreamReplayBuffer)``) with the usual arguments; it
    draws no random numbers of its own, so a seeded model is the same as with SB3's own buffer.

    The learner stores batches from its ingest thread while it trains in another: :meth:`add` and :meth:`sample`
    hold ``lock`` (callers that add many transitions may hold it around the whole batch; it is re-entrant).
    ``sample_limit`` (when set, and the buffer has not wrapped) restricts sampling to the first ``sample_limit``
    slots: a training iteration due at the ``k``-th transition then samples what SB3's ``learn()`` would have
    had at that step, however many transitions arrived meanwhile.
    """

    def __init__(self, buffer_size: int, observation_space: Any, action_space: Any, *args: Any, **kwargs: Any) -> None:
        """:param buffer_size: capacity in transitions
        :param observation_space: the environment's observation space
        :param action_space: the environment's action space
        :param args: further positional arguments of SB3's ReplayBuffer
        :param kwargs: further keyword arguments of SB3's ReplayBuffer (``n_envs`` must be 1)
        """
        super().__init__(buffer_size, observation_space, action_space, *args, **kwargs)
        if self.n_envs != 1:
            raise ValueError("StreamReplayBuffer holds one stream of transitions at a time (n_envs=1)")
        n = self.buffer_size
        self.provenance_actor = np.full(n, -1, dtype=np.int32)
        self.provenance_step = np.full(n, -1, dtype=np.int64)
        self.intervened = np.zeros(n, dtype=np.uint8)
        self.clipped = np.zeros(n, dtype=np.uint8)
        self.lock = threading.RLock()
        self.sample_limit: int | None = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("lock", None)  # not picklable; a loaded buffer gets a new one
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.lock = threading.RLock()
        self.__dict__.setdefault("sample_limit", None)

    def sample(self, batch_size: int, env: Any = None):
        """SB3's ``sample`` (uniform over the stored slots), under ``lock`` and within ``sample_limit``.

        :param batch_size: transitions in the minibatch
        :param env: SB3's VecNormalize (unused by the learner)
        """
        with self.lock:
            if self.full or self.sample_limit is None or self.optimize_memory_usage:
                return super().sample(batch_size, env=env)
            batch_inds = np.random.randint(0, max(1, min(self.pos, self.sample_limit)), size=batch_size)
            return self._get_samples(batch_inds, env=env)

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray, done: np.ndarray,
            infos: list[dict[str, Any]], *, intervened: bool | int = 0, clipped: bool | int = 0, actor: int = -1,
            step: int = -1) -> None:
        """SB3's ``add`` for one transition, and the slot's flags and provenance.

        :param obs: observation, shape (1, obs_dim)
        :param next_obs: next observation, shape (1, obs_dim)
        :param action: action stored for training, shape (1, act_dim)
        :param reward: reward, shape (1,)
        :param done: terminated or truncated, shape (1,)
        :param infos: one info dict (``TimeLimit.truncated``)
        :param intervened: the human corrected this step (the action is the human's)
        :param clipped: the safety layer clipped the action
        :param actor: provenance code of the actor stream (-1: unknown)
        :param step: the transition's running index in that actor's stream (-1: unknown)
        """
        with self.lock:
            slot = self.pos
            super().add(obs, next_obs, action, reward, done, infos)
            self.provenance_actor[slot] = actor
            self.provenance_step[slot] = step
            self.intervened[slot] = intervened
            self.clipped[slot] = clipped

    def add_batch(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray,
                  done: np.ndarray, timeout: np.ndarray, *, intervened: np.ndarray, clipped: np.ndarray, actor: int,
                  first_step: int) -> None:
        """``len(obs)`` transitions at once, into the same slots and with the same values as that many calls of
        :meth:`add` (wrapping around a full buffer the same way), without a Python call per transition.

        :param obs: observations, shape (n, obs_dim)
        :param next_obs: next observations, shape (n, obs_dim)
        :param action: stored actions, shape (n, act_dim)
        :param reward: rewards, shape (n,)
        :param done: terminated or truncated, shape (n,)
        :param timeout: truncated by the time limit and not terminated (SB3's ``TimeLimit.truncated``), shape (n,)
        :param intervened: per transition: the human corrected it
        :param clipped: per transition: the safety layer clipped the action
        :param actor: provenance code of the actor stream
        :param first_step: the running index of the first transition in that actor's stream
        """
        if self.optimize_memory_usage:
            raise ValueError("StreamReplayBuffer.add_batch does not support optimize_memory_usage")
        n, i = len(obs), 0
        with self.lock:
            while i < n:
                k = min(n - i, self.buffer_size - self.pos)
                dst, src = slice(self.pos, self.pos + k), slice(i, i + k)
                self.observations[dst, 0] = obs[src]
                self.next_observations[dst, 0] = next_obs[src]
                self.actions[dst, 0] = action[src]
                self.rewards[dst, 0] = reward[src]
                self.dones[dst, 0] = done[src]
                if self.handle_timeout_termination:
                    self.timeouts[dst, 0] = timeout[src]
                self.provenance_actor[dst] = actor
                self.provenance_step[dst] = first_step + np.arange(i, i + k)
                self.intervened[dst] = intervened[src]
                self.clipped[dst] = clipped[src]
                self.pos += k
                i += k
                if self.pos == self.buffer_size:
                    self.full, self.pos = True, 0

    def side_arrays(self) -> dict[str, np.ndarray]:
        """The per-slot arrays by name (:data:`SIDE_ARRAYS`), whole buffer (empty slots: provenance -1)."""
        return {"provenance_actor": self.provenance_actor, "provenance_step": self.provenance_step,
                "intervened": self.intervened, "clipped": self.clipped}
