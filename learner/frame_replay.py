"""A replay buffer for image observations that stores each camera frame once (issue 37, point 3).

Observations are a ``gymnasium.spaces.Dict`` of named cameras (uint8 H x W x C boxes, e.g. ``pixels/front``) and
one float32 state vector (``state``). SB3's ``DictReplayBuffer`` stores observation and next observation apart:
every frame twice. :class:`FrameReplayBuffer` is the learner's :class:`~khgrl.learner.replay.StreamReplayBuffer`
(its slots, provenance, per-actor shares, RLPD sampling -- inherited, not forked: every slot write goes through
its ``_write``, which this class extends) whose state vectors are its ordinary arrays and whose slots hold two
frame ids, ``obs_frame`` and ``next_frame``, into a :class:`~khgrl.learner.frame_store.FrameStore`.

**Storing** (:meth:`FrameReplayBuffer.add_frames`): a batch in the batch form of :mod:`khgrl.learner.frame_batch`
(each frame once; ``obs_frame[0] == PREV``: "row 0's observation is the previous batch's last next observation").
After every batch whose last row did not end its episode the buffer pins that row's next frame (one reference per
actor stream) with the step the stream goes on at; a PREV batch at another ``first_step`` (a batch lost between) is
refused. :meth:`add_batch` takes per-row observations as the other buffers do and packs them (row 0 continues
when the pin is at ``first_step`` and its pixels equal row 0's).

**Frames alive, the capacity.** Within one actor stream the slots alive are the newest of that stream (first in,
first out until full; then a batch evicts the *oldest* slots of an actor, :meth:`StreamReplayBuffer.queues`), i.e.
a run of consecutive steps. Every frame alive is some alive slot's next frame, or an observation that is no alive
slot's next frame -- the first observation of an episode that started in the run, or the run's head whose
predecessor was evicted -- or a pin whose slot was evicted. So, with E episode starts in the buffer and A streams,
``live <= buffer_size + E + 2 A``. Episodes of at least ``min_episode_steps`` steps give
``E <= buffer_size / min_episode_steps``; :func:`frame_capacity` adds ``2 * max_streams``. (A batch holds its own
frames until it is stored: only a batch larger than its actor's share, which evicts its own rows, goes above the
bound.) Beyond it :class:`~khgrl.learner.frame_store.FrameStoreFull` says so. Two 128x128x3 cameras: 98,304 bytes
per frame; 100,000 transitions of 100-step episodes hold 1.01 frames a transition, 9.95 GB with the per-slot
arrays against SB3's 19.7 GB (:mod:`khgrl.benchmarks.frame_replay`, ``docs/frame_replay.json``); the store
allocates ``frame_capacity`` frames, 10.3 GB with ``min_episode_steps`` 20 (pages committed as frames are written);
a checkpoint pickles, and its copy holds, the live frames only.

Save and load: the store, the frame ids and the pins are attributes, pickled with the buffer as the side arrays
are (:mod:`khgrl.learner.checkpoint`); ``copy.copy`` (the checkpoint's ``copy_buffer``) copies the store too.
:func:`khgrl.learner.sound.drop_bad_rows` moves :meth:`FrameReplayBuffer.frame_arrays` too and calls :meth:`recount`.
From the wire (:meth:`add_frames` with ``dedupe``): row 0's frame, always sent, is the pin's when pixel-equal.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from gymnasium import spaces
from khgrl.learner.frame_batch import PREV, pack_frames, split_space
from khgrl.learner.frame_store import FrameStore
from khgrl.learner.replay import StreamReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples

__all__ = ["FrameReplayBuffer", "frame_capacity"]


def frame_capacity(buffer_size: int, min_episode_steps: int, max_streams: int) -> int:
    """Frames a buffer can hold alive (the module docstring's bound): ``buffer_size + ceil(buffer_size /
    min_episode_steps) + 2 * max_streams``.

    :param buffer_size: slots
    :param min_episode_steps: the shortest episode the task has
    :param max_streams: actor streams storing into the buffer at most
    """
    return int(buffer_size + math.ceil(buffer_size / max(1, min_episode_steps)) + 2 * max(1, max_streams))


class _Incoming(NamedTuple):
    """A batch being stored: its frames, rows' indices, the ids its frames got (-1: not stored yet), the pin."""
    frames: dict[str, np.ndarray]
    obs_frame: np.ndarray
    next_frame: np.ndarray
    ids: np.ndarray
    prev: int


class FrameReplayBuffer(StreamReplayBuffer):
    """:class:`StreamReplayBuffer` for Dict observations of cameras and a state vector, each frame stored once
    (the module docstring). Built by SB3 (``replay_buffer_class=FrameReplayBuffer``) or directly.

    :param buffer_size: capacity in transitions
    :param observation_space: Dict of uint8 H x W x C cameras and a float32 state vector
    :param action_space: the action space
    :param args: further positional arguments of SB3's ReplayBuffer (device, n_envs)
    :param state_key: the state vector's key
    :param min_episode_steps: the task's shortest episode (sizes the frame store: :func:`frame_capacity`)
    :param max_streams: actor streams storing at most (sizes the frame store)
    :param kwargs: ``prior_fraction`` and SB3's keyword arguments (``optimize_memory_usage`` must be False)
    """

    def __init__(self, buffer_size: int, observation_space: spaces.Dict, action_space: Any, *args: Any,
                 state_key: str = "state", min_episode_steps: int = 20, max_streams: int = 64,
                 **kwargs: Any) -> None:
        cameras, state_space = split_space(observation_space, state_key)
        if kwargs.get("optimize_memory_usage"):
            raise ValueError("FrameReplayBuffer stores each frame once already: optimize_memory_usage is not needed")
        super().__init__(buffer_size, state_space, action_space, *args, **kwargs)
        self.observation_space = observation_space
        self.state_key, self.cameras = state_key, cameras
        self.obs_frame = np.full(self.buffer_size, -1, dtype=np.int64)
        self.next_frame = np.full(self.buffer_size, -1, dtype=np.int64)
        capacity = frame_capacity(self.buffer_size, min_episode_steps, max_streams)
        self.store = FrameStore({k: observation_space.spaces[k].shape for k in cameras}, capacity)
        self.pins: dict[int, tuple[int, int]] = {}  # actor code -> (frame id, the step its next batch starts at)
        self._incoming: _Incoming | None = None

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state.pop("_incoming", None)
        return state

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        self._incoming = None

    def __copy__(self) -> FrameReplayBuffer:
        """An independent copy: its arrays, frame store and pins copied (the checkpoint's ``copy_buffer`` copies
        only the arrays that are the buffer's own attributes)."""
        out = type(self).__new__(type(self))
        out.__setstate__({k: v.copy() if isinstance(v, np.ndarray) else v for k, v in self.__getstate__().items()})
        out.store, out.pins = self.store.copy(), dict(self.pins)
        return out

    def add_frames(self, frames: dict[str, np.ndarray], obs_frame: np.ndarray, next_frame: np.ndarray,
                   state: np.ndarray, next_state: np.ndarray, action: np.ndarray, reward: np.ndarray,
                   done: np.ndarray, timeout: np.ndarray, *, intervened: np.ndarray, clipped: np.ndarray, actor: int,
                   first_step: int, dedupe: bool = False) -> None:
        """One batch of one actor's consecutive transitions in the batch form (the module docstring), into the
        slots :meth:`StreamReplayBuffer.add_batch` chooses.

        :param frames: camera -> the batch's distinct frames, shape (m, H, W, C)
        :param obs_frame: per row: index of its observation's frame (row 0 may be :data:`PREV`)
        :param next_frame: per row: index of its next observation's frame
        :param state: state vectors, shape (n, state_dim)
        :param next_state: next state vectors, shape (n, state_dim)
        :param action: stored actions, shape (n, act_dim)
        :param reward: rewards, shape (n,)
        :param done: terminated or truncated, shape (n,)
        :param timeout: truncated and not terminated, shape (n,)
        :param intervened: per transition: the human corrected it
        :param clipped: per transition: the safety layer clipped the action
        :param actor: provenance code of the actor stream
        :param first_step: the running index of the first transition in that stream (-1: unknown)
        :param dedupe: row 0's observation frame, when it equals the stream's pinned frame at ``first_step``, is
            that frame (the module docstring: a batch from the wire)
        :raises ValueError: indices out of range, or PREV without a pin for this stream at ``first_step``
        :raises FrameStoreFull: more frames alive than the store was sized for (``min_episode_steps``,
            ``max_streams``); the batch is then stored in part and the buffer is not to be used further
        """
        obs_frame, next_frame = np.asarray(obs_frame, dtype=np.int64), np.asarray(next_frame, dtype=np.int64)
        n, m = len(state), len(next(iter(frames.values())))
        if not len(obs_frame) == len(next_frame) == n:
            raise ValueError(f"{n} rows, {len(obs_frame)} obs_frame and {len(next_frame)} next_frame indices")
        if n == 0:
            return
        if np.any(obs_frame[1:] < 0) or np.any(obs_frame >= m) or np.any(next_frame < 0) or np.any(next_frame >= m):
            raise ValueError(f"frame indices outside the batch's {m} frames (PREV only for row 0)")
        with self.lock:
            prev = -1
            if dedupe and obs_frame[0] >= 0 and self._continues(actor, first_step, frames, int(obs_frame[0])):
                obs_frame = obs_frame.copy()
                obs_frame[0] = PREV
            if obs_frame[0] == PREV:
                pin = self.pins.get(actor)
                if pin is None or (first_step >= 0 and pin[1] != first_step):
                    raise ValueError(f"row 0 continues the previous batch of actor code {actor}, but the buffer "
                                     f"holds no frame of that stream ending before step {first_step} (pin {pin})")
                prev = pin[0]
            self._incoming = _Incoming(frames, obs_frame, next_frame, np.full(m, -1, dtype=np.int64), prev)
            try:
                super().add_batch(state, next_state, action, reward, done, timeout, intervened=intervened,
                                  clipped=clipped, actor=actor, first_step=first_step)
                last = None if done[-1] else int(self._incoming.ids[next_frame[-1]])
                self._pin(actor, last, first_step + n if first_step >= 0 else -1)
            finally:
                ids = self._incoming.ids
                self._incoming = None
                self.store.decref(ids[ids >= 0])  # the batch's own references

    def add_batch(self, obs: dict[str, np.ndarray], next_obs: dict[str, np.ndarray], action: np.ndarray,
                  reward: np.ndarray, done: np.ndarray, timeout: np.ndarray, *, intervened: np.ndarray,
                  clipped: np.ndarray, actor: int, first_step: int, continues: bool | None = None) -> None:
        """A batch of one actor's consecutive transitions with per-row observations (Dicts of arrays with a
        leading row axis): packed (:func:`pack_frames`) and stored by :meth:`add_frames`.

        :param obs: key -> observations, shape (n, ...)
        :param next_obs: key -> next observations, shape (n, ...)
        :param action: stored actions, shape (n, act_dim)
        :param reward: rewards, shape (n,)
        :param done: terminated or truncated, shape (n,)
        :param timeout: truncated and not terminated, shape (n,)
        :param intervened: per transition: the human corrected it
        :param clipped: per transition: the safety layer clipped the action
        :param actor: provenance code of the actor stream
        :param first_step: the running index of the first transition in that stream
        :param continues: row 0's observation is the stream's pinned frame (None: when the pin is at ``first_step``
            and its pixels equal row 0's)
        """
        with self.lock:
            if continues is None:
                continues = len(done) > 0 and self._continues(actor, first_step, obs, 0)
            frames, obs_frame, next_frame = pack_frames(obs, next_obs, done, self.cameras, continues)
            self.add_frames(frames, obs_frame, next_frame, obs[self.state_key], next_obs[self.state_key], action,
                            reward, done, timeout, intervened=intervened, clipped=clipped, actor=actor,
                            first_step=first_step)

    def add(self, obs: dict[str, np.ndarray], next_obs: dict[str, np.ndarray], action: np.ndarray,
            reward: np.ndarray, done: np.ndarray, infos: list[dict[str, Any]], *, intervened: bool | int = 0,
            clipped: bool | int = 0, actor: int = -1, step: int = -1) -> None:
        """SB3's ``add`` of one transition (Dict observations with a leading axis of 1), as a batch of one row.

        :param obs: key -> observation, shape (1, ...)
        :param next_obs: key -> next observation, shape (1, ...)
        :param action: action, shape (1, act_dim)
        :param reward: reward, shape (1,)
        :param done: terminated or truncated, shape (1,)
        :param infos: one info dict (``TimeLimit.truncated``)
        :param intervened: the human corrected this step
        :param clipped: the safety layer clipped the action
        :param actor: provenance code of the actor stream
        :param step: the transition's running index in that stream
        """
        timeout = np.array([bool(infos[0].get("TimeLimit.truncated", False))]) if infos else np.zeros(1, dtype=bool)
        shape = {k: self.observation_space[k].shape for k in obs}
        self.add_batch({k: np.asarray(v).reshape(1, *shape[k]) for k, v in obs.items()},
                       {k: np.asarray(v).reshape(1, *shape[k]) for k, v in next_obs.items()},
                       np.asarray(action).reshape(1, -1), np.asarray(reward).reshape(1), np.asarray(done).reshape(1),
                       timeout, intervened=np.array([intervened]), clipped=np.array([clipped]), actor=actor,
                       first_step=step)

    def _write(self, dst: slice | np.ndarray, cols: tuple, i: int, k: int, actor: int, first_step: int) -> None:
        """StreamReplayBuffer's write of rows ``i .. i+k`` into slots ``dst``, and their frames: the overwritten
        slots' references dropped, the rows' frames stored (once per batch) and referenced."""
        inc = self._incoming
        if inc is None:
            raise RuntimeError("FrameReplayBuffer stores through add_frames, add_batch or add")
        super()._write(dst, cols, i, k, actor, first_step)
        old = np.concatenate([self.obs_frame[dst], self.next_frame[dst]])
        self.store.decref(old[old >= 0])  # (a frame the next rows need is held by the batch or the pin)
        o_idx, n_idx = inc.obs_frame[i:i + k], inc.next_frame[i:i + k]
        used = np.concatenate([o_idx[o_idx >= 0], n_idx])
        need = np.unique(used[inc.ids[used] < 0])
        if len(need):
            inc.ids[need] = self.store.put_many({c: inc.frames[c][need] for c in self.cameras})
        o = np.where(o_idx >= 0, inc.ids[np.maximum(o_idx, 0)], inc.prev)
        nx = inc.ids[n_idx]
        self.obs_frame[dst], self.next_frame[dst] = o, nx
        self.store.incref(np.concatenate([o, nx]))

    def _continues(self, actor: int, first_step: int, frames: dict[str, np.ndarray], i: int) -> bool:
        """Whether the actor stream's pin is at ``first_step`` and its pixels are ``frames[k][i]`` for every camera."""
        pin = self.pins.get(actor)
        return (pin is not None and (first_step < 0 or pin[1] == first_step)
                and all(np.array_equal(self.store.frames[k][pin[0]], frames[k][i]) for k in self.cameras))

    def _pin(self, actor: int, frame: int | None, step: int) -> None:
        """Pin ``frame`` as the actor stream's last next observation (None: its episode ended; no pin)."""
        old = self.pins.pop(actor, None)
        if frame is not None:
            self.store.incref(np.array([frame]))
            self.pins[actor] = (frame, step)
        if old is not None:
            self.store.decref(np.array([old[0]]))

    def _get_samples(self, batch_inds: np.ndarray, env: Any = None) -> DictReplayBufferSamples:
        """SB3's DictReplayBuffer samples of the slots ``batch_inds``: images uint8, state float32 (the same
        random draw as SB3's ``_get_samples``)."""
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        obs = self.store.get(self.obs_frame[batch_inds])
        nxt = self.store.get(self.next_frame[batch_inds])
        obs[self.state_key] = self.observations[batch_inds, env_indices]
        nxt[self.state_key] = self.next_observations[batch_inds, env_indices]
        obs, nxt = self._normalize_obs(obs, env), self._normalize_obs(nxt, env)
        keys = list(self.observation_space.spaces)
        done = self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])
        return DictReplayBufferSamples(  # (the gathered observations are fresh arrays: no second copy on a CPU)
            observations={key: self.to_torch(obs[key], copy=False) for key in keys},
            actions=self.to_torch(self.actions[batch_inds, env_indices]),
            next_observations={key: self.to_torch(nxt[key], copy=False) for key in keys},
            dones=self.to_torch(done.reshape(-1, 1)),
            rewards=self.to_torch(self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env)))

    def sample_into(self, out: np.ndarray) -> None:
        """Not for image observations (flat float32 rows): use :meth:`sample`. :param out: unused"""
        raise NotImplementedError("FrameReplayBuffer holds images: sample() gives the minibatch, not sample_into")

    def frame_arrays(self) -> dict[str, np.ndarray]:
        """The per-slot frame ids by name (-1: an empty slot)."""
        return {"obs_frame": self.obs_frame, "next_frame": self.next_frame}

    def recount(self) -> None:
        """Rebuild the store's reference counts and free list from the slots' frame ids and the pins (after the
        slots were moved about: :func:`~khgrl.learner.sound.drop_bad_rows`)."""
        with self.lock:
            stored = self.buffer_size if self.full else self.pos
            held = [self.obs_frame[:stored], self.next_frame[:stored],
                    np.array([p[0] for p in self.pins.values()], dtype=np.int64)]
            self.store.recount(np.concatenate(held))

    def nbytes(self) -> int:
        """Bytes the buffer's arrays take when full: the frame store and the per-slot arrays."""
        per_slot = sum(a.nbytes for a in (self.observations, self.next_observations, self.actions, self.rewards,
                                          self.dones, self.timeouts, self.obs_frame, self.next_frame))
        return self.store.nbytes + per_slot + sum(a.nbytes for a in self.side_arrays().values())
