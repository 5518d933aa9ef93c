"""The learner's replay buffer: SB3's :class:`ReplayBuffer` plus what the learner knows about each slot.

Besides SB3's arrays, every slot records whether the human intervened on that transition (the stored action
is then the human's a_h), whether the action was clipped by the safety layer, and its provenance: the actor
stream it came from (a code into the learner's stream table, ``-1`` for an empty slot) and the transition's
running index in that actor's stream. :meth:`StreamReplayBuffer.add` writes them in the same slot as SB3's
fields, so they can never drift apart, and they travel inside the buffer: TQC builds this class through
``replay_buffer_class`` and ``save_replay_buffer``/``load_replay_buffer`` save and load them with the rest.

Shares: until the buffer is full it fills first in, first out, exactly as SB3's. Once full, each actor id holding
slots (plus one that adds) has a share of ``buffer_size // owners`` slots: a batch overwrites the oldest slots of
its own actor while that actor holds at least its share, and otherwise the oldest slots of the actor most over its
share. So one actor cannot evict another's data below its share, however much it sends. With one actor that actor
always holds every slot (at least its share), so it overwrites its own oldest slot: SB3's first in, first out.

Sampling: uniform over the stored slots (SB3's, ``prior_fraction`` 0), or RLPD's symmetric sampling (Ball et al.
2023, "Efficient Online Reinforcement Learning with Offline Data", ikostrikov/rlpd@c90fd4b:train_finetuning.py:36
``offline_ratio`` 0.5; HIL-SERL's learner takes ``batch_size // 2`` from each of its two buffers,
rail-berkeley/hil-serl@5d02aed:examples/train_rlpd.py:288-302): a share ``prior_fraction`` of each minibatch from
the *prior* slots -- those stored with ``intervened`` = 1: the human's interventions and takeovers and the
demonstrations the actor replays as intervened transitions -- and the rest uniformly from all slots (HIL-SERL
stores an intervention in both its buffers, train_rlpd.py:198-201: all slots are the online data).

One module of ~350 lines on purpose: one buffer class, SB3's ReplayBuffer with the learner's per-slot bookkeeping,
which every sampling mode reads.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer

__all__ = ["StreamReplayBuffer", "SIDE_ARRAYS", "PRIOR_FRACTIONS", "prior_fraction"]

# name of each per-slot array as exported by :meth:`StreamReplayBuffer.side_arrays` (and load_checkpoint_arrays)
SIDE_ARRAYS = ("provenance_actor", "provenance_step", "intervened", "clipped")

# ``[tqc] sampling`` -> share of each minibatch drawn from the prior (intervened) slots (module docstring: RLPD's 0.5)
PRIOR_FRACTIONS = {"uniform": 0.0, "rlpd": 0.5}


def prior_fraction(sampling: str) -> float:
    """The buffer's ``prior_fraction`` for a ``[tqc] sampling`` value.

    :param sampling: ``uniform`` or ``rlpd``
    :raises ValueError: another value
    """
    if sampling not in PRIOR_FRACTIONS:
        raise ValueError(f"unknown sampling {sampling!r}: one of {', '.join(PRIOR_FRACTIONS)}")
    return PRIOR_FRACTIONS[sampling]


class StreamReplayBuffer(ReplayBuffer):
    """A replay buffer for one environment (``n_envs=1``) whose slots also hold the intervention and clip flags
    and the provenance (actor code, the actor's transition index) of the transition stored there.

    Constructed by SB3 (``TQC(..., replay_buffer_class=StreamReplayBuffer)``) with the usual arguments and
    (``replay_buffer_kwargs``) ``prior_fraction``. With ``prior_fraction`` 0 it draws exactly the random numbers
    SB3's own buffer draws, so a seeded model is the same as with SB3's buffer; above 0 a minibatch is RLPD's
    symmetric sample (the module docstring, :meth:`sample`). ``sampled_prior`` and ``sampled_online`` count the
    transitions drawn from each part (pickled with the buffer).

    The learner stores batches from its ingest thread while it trains in another: :meth:`add` and :meth:`sample`
    hold ``lock`` (callers that add many transitions may hold it around the whole batch; it is re-entrant).
    ``sample_limit`` (when set, and the buffer has not wrapped) restricts sampling to the first ``sample_limit``
    slots: a training iteration due at the ``k``-th transition then samples what SB3's ``learn()`` would have
    had at that step, however many transitions arrived meanwhile.
    """

    def __init__(self, buffer_size: int, observation_space: Any, action_space: Any, *args: Any,
                 prior_fraction: float = 0.0, **kwargs: Any) -> None:
        """:param buffer_size: capacity in transitions
        :param observation_space: the environment's observation space
        :param action_space: the environment's action space
        :param args: further positional arguments of SB3's ReplayBuffer
        :param prior_fraction: share of each minibatch drawn from the intervened slots (0: SB3's uniform sampling;
            RLPD: 0.5, :data:`PRIOR_FRACTIONS`)
        :param kwargs: further keyword arguments of SB3's ReplayBuffer (``n_envs`` must be 1)
        """
        super().__init__(buffer_size, observation_space, action_space, *args, **kwargs)
        if self.n_envs != 1:
            raise ValueError("StreamReplayBuffer holds one stream of transitions at a time (n_envs=1)")
        self.prior_fraction = self.check_fraction(prior_fraction)
        self.sampled_prior = 0  # transitions drawn from the prior (intervened) slots, all minibatches so far
        self.sampled_online = 0  # and uniformly from all slots
        self._writes = 0  # writes so far (the prior index's cache key)
        self._prior_index: tuple[tuple[int, int, bool], np.ndarray] | None = None  # (key, slots)
        n = self.buffer_size
        self.provenance_actor = np.full(n, -1, dtype=np.int32)
        self.provenance_step = np.full(n, -1, dtype=np.int64)
        self.intervened = np.zeros(n, dtype=np.uint8)
        self.clipped = np.zeros(n, dtype=np.uint8)
        self.lock = threading.RLock()
        self.sample_limit: int | None = None
        # the learner's stream table's codes (code -> {"actor", "stream"}): shares are per actor id, not per stream
        self.stream_codes: list[dict[str, str]] | None = None
        self._queues: dict[str, deque] | None = None  # once full: actor id -> its slots, oldest first

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        for name in ("lock", "stream_codes", "_queues", "_prior_index"):  # a loaded buffer gets a new lock, the
            state.pop(name, None)  # learner's codes, and rebuilds the slot queues and prior index (so old
        return state  # checkpoints load as new ones do)

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.lock = threading.RLock()
        for name, value in (("sample_limit", None), ("prior_fraction", 0.0), ("sampled_prior", 0),
                            ("sampled_online", 0), ("_writes", 0)):  # (a checkpoint of an older learner)
            self.__dict__.setdefault(name, value)
        self.stream_codes, self._queues, self._prior_index = None, None, None

    def check_fraction(self, fraction: float) -> float:
        """``fraction`` as a ``prior_fraction`` of this buffer (a float in [0, 1]).

        :param fraction: the share of a minibatch from the prior slots
        :raises ValueError: out of [0, 1], or above 0 with SB3's ``optimize_memory_usage``
        """
        fraction = float(fraction)
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"prior_fraction must be in [0, 1], not {fraction}")
        if fraction > 0 and self.optimize_memory_usage:
            raise ValueError("StreamReplayBuffer's prior sampling does not support optimize_memory_usage")
        return fraction

    def sample(self, batch_size: int, env: Any = None):
        """A minibatch under ``lock`` and within ``sample_limit``: SB3's ``sample`` (uniform over the stored slots;
        the same random draws) while ``prior_fraction`` is 0 or no prior slot can be sampled; else RLPD's symmetric
        sample: ``round(batch_size * prior_fraction)`` slots uniformly from the sampleable intervened slots, the
        rest uniformly from all sampleable slots (online part first, as HIL-SERL concatenates them).

        :param batch_size: transitions in the minibatch
        :param env: SB3's VecNormalize (unused by the learner)
        """
        with self.lock:
            inds = self._draw(batch_size)
            if inds is None:
                return super().sample(batch_size, env=env)
            return self._get_samples(inds, env=env)

    def sample_into(self, out: np.ndarray) -> None:
        """A minibatch as :meth:`sample` draws it (the same random numbers, in the same order), written as rows of
        ``out`` (shape ``(batch_size, width)``): observation, action, next observation, done-and-not-timeout,
        reward, side by side (:meth:`minibatch_width`) -- the numbers SB3's ``_get_samples`` puts into its
        five tensors, with no tensor made (the CUDA-graph learner copies ``out``, pinned, to the device at once).

        :param out: float32 rows to fill
        """
        batch_size = len(out)
        with self.lock:
            inds = self._draw(batch_size)
            if inds is None:  # (SB3's own uniform draw: ReplayBuffer.sample's bound)
                inds = np.random.randint(0, self.buffer_size if self.full else self.pos, size=batch_size)
            env_indices = np.random.randint(0, high=self.n_envs, size=(batch_size,))  # (_get_samples' draw)
            o, a = self.obs_shape[0], self.action_dim
            out[:, :o] = self.observations[inds, env_indices]
            out[:, o:o + a] = self.actions[inds, env_indices]
            out[:, o + a:2 * o + a] = self.next_observations[inds, env_indices]
            out[:, -2] = self.dones[inds, env_indices] * (1 - self.timeouts[inds, env_indices])
            out[:, -1] = self.rewards[inds, env_indices]

    def minibatch_width(self) -> int:
        """Columns of a :meth:`sample_into` row: observation, action, next observation, done, reward."""
        return 2 * int(self.obs_shape[0]) + int(self.action_dim) + 2

    def _draw(self, batch_size: int) -> np.ndarray | None:
        """The slots of a minibatch (the caller holds ``lock``), drawn as :meth:`sample` says; None: draw SB3's
        ``ReplayBuffer.sample`` itself (uniform over the whole stored buffer)."""
        limited = not (self.full or self.sample_limit is None or self.optimize_memory_usage)
        upper = max(1, min(self.pos, self.sample_limit)) if limited else None
        prior = self.prior_index(upper) if self.prior_fraction > 0 else None
        n_prior = int(round(batch_size * self.prior_fraction)) if prior is not None and len(prior) else 0
        self.sampled_prior += n_prior
        self.sampled_online += batch_size - n_prior
        if n_prior == 0:  # SB3's uniform sampling, its random draws exactly
            return None if not limited else np.random.randint(0, upper, size=batch_size)
        if upper is None:  # (SB3's bound: the whole buffer once full, else the stored slots)
            upper = self.buffer_size if self.full else self.pos
        online = np.random.randint(0, upper, size=batch_size - n_prior)
        chosen = prior[np.random.randint(0, len(prior), size=n_prior)]
        return np.concatenate([online, chosen])

    def prior_index(self, upper: int | None = None) -> np.ndarray:
        """The prior slots (``intervened`` = 1) among the stored ones, ascending: built with ``np.flatnonzero`` when
        first asked for after a write and cached until the next one (a sample costs a search, not a scan). Measured
        on a full buffer of 200,000 slots, a tenth of them prior, on a shared 2-core CPU: a minibatch of 256 takes
        0.13-0.15 ms either way with the index cached, 0.7 ms when a write came first (the rebuild) -- at most once
        per stored batch, against 20-30 ms for a gradient step on that CPU.

        :param upper: only the slots below this (None: all stored slots)
        """
        with self.lock:
            key = (self._writes, int(self.pos), bool(self.full))
            if self._prior_index is None or self._prior_index[0] != key:
                stored = self.buffer_size if self.full else self.pos
                self._prior_index = (key, np.flatnonzero(self.intervened[:stored]))
            slots = self._prior_index[1]
            return slots if upper is None else slots[:int(np.searchsorted(slots, upper))]

    def prior_slots(self) -> int:
        """How many stored transitions are prior data (``intervened`` = 1)."""
        with self.lock:
            return int(np.count_nonzero(self.intervened[:self.buffer_size if self.full else self.pos]))

    def sampling_info(self) -> dict[str, Any]:
        """What the learner's status reports of the sampling: ``prior_fraction``, ``prior_slots``, ``sampled_prior``,
        ``sampled_online``."""
        return dict(prior_fraction=self.prior_fraction, prior_slots=self.prior_slots(),
                    sampled_prior=self.sampled_prior, sampled_online=self.sampled_online)

    @property
    def prior_share(self) -> float:
        """The share of all transitions sampled so far that came from the prior part (0 before the first sample)."""
        total = self.sampled_prior + self.sampled_online
        return self.sampled_prior / total if total else 0.0

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
            self._queues = None  # (first in, first out here: the shares' queues are rebuilt when next needed)
            super().add(obs, next_obs, action, reward, done, infos)
            self._writes += 1
            self.provenance_actor[slot] = actor
            self.provenance_step[slot] = step
            self.intervened[slot] = intervened
            self.clipped[slot] = clipped

    def add_batch(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray,
                  done: np.ndarray, timeout: np.ndarray, *, intervened: np.ndarray, clipped: np.ndarray, actor: int,
                  first_step: int) -> None:
        """``len(obs)`` transitions at once: until the buffer is full into the same slots and with the same values as
        that many calls of :meth:`add`, without a Python call per transition; once full, into the slots the actor's
        share gives (see the module docstring: with one actor, the same slots as :meth:`add`).

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
        cols = (obs, next_obs, action, reward, done, timeout, intervened, clipped)
        n, i = len(obs), 0
        with self.lock:
            while i < n and not self.full:  # first in, first out until full
                k = min(n - i, self.buffer_size - self.pos)
                self._write(slice(self.pos, self.pos + k), cols, i, k, actor, first_step)
                self.pos += k
                i += k
                if self.pos == self.buffer_size:
                    self.full, self.pos = True, 0
            if i < n:
                self._add_shared(cols, i, n, actor, first_step)

    def _write(self, dst: slice | np.ndarray, cols: tuple, i: int, k: int, actor: int, first_step: int) -> None:
        """Write transitions ``i .. i+k`` of a batch into the slots ``dst``."""
        obs, next_obs, action, reward, done, timeout, intervened, clipped = cols
        src = slice(i, i + k)
        self._writes += 1  # (the prior index is rebuilt when next asked for)
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

    def owner(self, code: int) -> str:
        """The actor id a provenance code stands for (``#code`` without the learner's stream table).

        :param code: a provenance code (-1: unknown)
        """
        codes = self.stream_codes
        return codes[code]["actor"] if codes is not None and 0 <= code < len(codes) else f"#{code}"

    def queues(self) -> dict[str, deque]:
        """Once full: each actor id's slots, oldest first (built from the provenance when first needed: by stream
        code, then the actor's running index -- the order a full buffer was written in)."""
        if self._queues is None:
            order = np.lexsort((self.provenance_step, self.provenance_actor))
            codes = self.provenance_actor[order]
            queues: dict[str, deque] = {}
            bounds = np.flatnonzero(np.diff(codes)) + 1
            for part in np.split(order, bounds):
                queues.setdefault(self.owner(int(self.provenance_actor[part[0]])), deque()).extend(part.tolist())
            self._queues = queues
        return self._queues

    def _add_shared(self, cols: tuple, i: int, n: int, actor: int, first_step: int) -> None:
        """Transitions ``i .. n`` of a batch into a full buffer, by the shares (the module docstring)."""
        queues = self.queues()
        me = self.owner(actor)
        mine = queues.setdefault(me, deque())
        slots = np.empty(0, dtype=np.int64)
        while i < n:
            share = self.buffer_size // len(queues)  # (``me`` among them)
            if len(mine) >= share:
                victim, k = mine, min(n - i, len(mine))
            else:
                other = max((a for a in queues if a != me), key=lambda a: len(queues[a]))
                victim = queues[other]
                k = max(1, min(n - i, share - len(mine), len(victim) - share))
            slots = np.fromiter((victim.popleft() for _ in range(k)), dtype=np.int64, count=k)
            self._write(slots, cols, i, k, actor, first_step)
            mine.extend(slots.tolist())
            i += k
            for a in [a for a, q in queues.items() if not q]:
                del queues[a]
        self.pos = int(slots[-1] + 1) % self.buffer_size

    def shares(self) -> dict[str, int]:
        """Slots held per actor id (all stored transitions)."""
        with self.lock:
            if not self.full:
                slots = self.provenance_actor[:self.pos]
                codes, counts = np.unique(slots, return_counts=True)
                out: dict[str, int] = {}
                for c, m in zip(codes.tolist(), counts.tolist()):
                    out[self.owner(c)] = out.get(self.owner(c), 0) + m
                return out
            return {a: len(q) for a, q in self.queues().items()}

    def side_arrays(self) -> dict[str, np.ndarray]:
        """The per-slot arrays by name (:data:`SIDE_ARRAYS`), whole buffer (empty slots: provenance -1)."""
        return {"provenance_actor": self.provenance_actor, "provenance_step": self.provenance_step,
                "intervened": self.intervened, "clipped": self.clipped}
