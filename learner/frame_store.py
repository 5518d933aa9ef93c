"""A bounded, reference-counted pool of camera frames, each stored once (issue 37, point 3).

SB3's ``DictReplayBuffer`` keeps every image twice, once as a slot's observation and once as its next observation:
100,000 transitions of two 128x128x3 cameras take ~20 GB. In one actor's stream the next observation of step ``t``
is the observation of step ``t + 1``, so a replay that stores frames here and keeps two frame ids per slot
(:class:`~khgrl.learner.frame_replay.FrameReplayBuffer`) holds each frame once: ~10 GB.

:class:`FrameStore` preallocates, per camera, one uint8 array of ``capacity`` frames (``np.zeros``: pages are
committed by the OS as frames are written, so resident memory grows with the frames stored). A frame has a
reference count: :meth:`put_many` stores frames with one reference each (the caller's), :meth:`incref` and
:meth:`decref` add and drop references (a slot referencing the frame, an actor's pinned last frame), and a frame
whose count drops to 0 goes back to the free list, whose ids :meth:`put_many` reuses (last freed, first reused).
:meth:`get` gathers a minibatch with one fancy index per camera. Dropping a reference the frame does not have
raises (a double free is a bug, never silently absorbed); so does storing a frame when none is free
(:class:`FrameStoreFull`, naming the capacity: the owner sized it by a bound it states).

Everything is numpy arrays and ints: the store pickles with the replay buffer that owns it (SB3's
``save_replay_buffer``) and :meth:`copy` makes an independent copy (a checkpoint's :func:`copy_buffer`). Both hold
the live frames only (``__getstate__``): a checkpoint of a store sized for 100,000 transitions that holds 5,000
writes 5,000 frames, not 100,000, and a copy touches no page the original did not.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FrameStore", "FrameStoreFull"]


class FrameStoreFull(RuntimeError):
    """More frames alive than the store's capacity."""


class FrameStore:
    """``capacity`` frames per camera, reference-counted, with a free list.

    :param shapes: camera name -> frame shape (H, W, C)
    :param capacity: frames held at most
    :param dtype: the frames' dtype (uint8 pixels)
    """

    def __init__(self, shapes: dict[str, tuple[int, ...]], capacity: int, dtype: np.dtype = np.uint8) -> None:
        if capacity < 1:
            raise ValueError(f"a FrameStore needs a capacity of at least 1 frame, not {capacity}")
        if not shapes:
            raise ValueError("a FrameStore needs at least one camera")
        self.capacity = int(capacity)
        self.shapes = {k: tuple(int(d) for d in s) for k, s in shapes.items()}
        self.frames = {k: np.zeros((self.capacity, *s), dtype=dtype) for k, s in self.shapes.items()}
        self.refs = np.zeros(self.capacity, dtype=np.int32)
        # the free ids as a stack: _free[:_top]; popped from the top (the lowest ids first on a fresh store)
        self._free = np.arange(self.capacity - 1, -1, -1, dtype=np.int64)
        self._top = self.capacity

    @property
    def live(self) -> int:
        """Frames held (referenced at least once)."""
        return self.capacity - self._top

    @property
    def nbytes(self) -> int:
        """Bytes of the preallocated frame arrays, reference counts and free list (what a full store holds)."""
        return sum(a.nbytes for a in self.frames.values()) + self.refs.nbytes + self._free.nbytes

    @property
    def frame_bytes(self) -> int:
        """Bytes of one frame over all cameras."""
        return sum(a[0].nbytes for a in self.frames.values())

    def put(self, frames: dict[str, np.ndarray]) -> int:
        """Store one frame (one image per camera) with one reference; its id.

        :param frames: camera name -> image of that camera's shape
        :raises FrameStoreFull: no free id
        """
        return int(self.put_many({k: np.asarray(v)[None] for k, v in frames.items()})[0])

    def put_many(self, frames: dict[str, np.ndarray]) -> np.ndarray:
        """Store ``n`` frames, one reference each; their ids (int64, shape (n,)).

        :param frames: camera name -> images, shape (n, *shape) (every camera of the store, the same n)
        :raises FrameStoreFull: fewer than n free ids (nothing is stored then)
        :raises ValueError: missing cameras or mismatched shapes
        """
        if set(frames) != set(self.frames):
            raise ValueError(f"frames for cameras {sorted(frames)}, the store holds {sorted(self.frames)}")
        n = len(next(iter(frames.values())))
        for k, v in frames.items():
            if v.shape != (n, *self.shapes[k]):
                raise ValueError(f"camera {k!r}: frames of shape {v.shape}, expected {(n, *self.shapes[k])}")
        if n > self._top:
            raise FrameStoreFull(f"FrameStore: {n} frames to store, {self._top} free of {self.capacity} (more frames "
                                 f"alive than the bound the store was sized for)")
        ids = self._free[self._top - n:self._top][::-1].copy()
        self._top -= n
        for k, v in frames.items():
            self.frames[k][ids] = v
        self.refs[ids] = 1
        return ids

    def incref(self, ids: np.ndarray) -> None:
        """One more reference to each id (an id repeated gets one per occurrence).

        :param ids: frame ids, all alive
        :raises ValueError: an id that is not alive
        """
        ids = np.asarray(ids, dtype=np.int64).ravel()
        if len(ids) == 0:
            return
        if np.any(self.refs[ids] <= 0):
            raise ValueError(f"FrameStore.incref of frames not alive: {np.unique(ids[self.refs[ids] <= 0])[:8]}")
        np.add.at(self.refs, ids, 1)

    def decref(self, ids: np.ndarray) -> None:
        """Drop one reference of each id (per occurrence); frames left with none are freed.

        :param ids: frame ids
        :raises ValueError: more references dropped than a frame has (nothing is changed then)
        """
        ids = np.asarray(ids, dtype=np.int64).ravel()
        if len(ids) == 0:
            return
        uniq, counts = np.unique(ids, return_counts=True)
        if np.any(self.refs[uniq] < counts):
            bad = uniq[self.refs[uniq] < counts]
            raise ValueError(f"FrameStore.decref drops more references than frames {bad[:8]} have")
        self.refs[uniq] -= counts.astype(np.int32)
        freed = uniq[self.refs[uniq] == 0]
        self._free[self._top:self._top + len(freed)] = freed
        self._top += len(freed)

    def get(self, ids: np.ndarray) -> dict[str, np.ndarray]:
        """The frames of ``ids`` per camera (copies, shape (len(ids), *shape)): one fancy index per camera.

        :param ids: frame ids (alive)
        """
        return {k: a[ids] for k, a in self.frames.items()}

    def recount(self, ids: np.ndarray) -> None:
        """Set every reference count from the references that exist (``ids``: each occurrence one reference;
        -1 entries are ignored) and rebuild the free list: what an owner calls after moving its slots about.

        :param ids: all references held, flattened (slots' frame ids, pins)
        """
        ids = np.asarray(ids, dtype=np.int64).ravel()
        ids = ids[ids >= 0]
        self.refs[:] = np.bincount(ids, minlength=self.capacity).astype(np.int32)
        free = np.flatnonzero(self.refs == 0)[::-1]
        self._free[:len(free)] = free
        self._top = len(free)

    def __getstate__(self) -> dict:
        """What pickles: everything but the frames of free ids (the live frames, with their ids)."""
        live = np.flatnonzero(self.refs > 0)
        return {**self.__dict__, "frames": {k: a[live] for k, a in self.frames.items()}, "live_ids": live}

    def __setstate__(self, state: dict) -> None:
        """A store from :meth:`__getstate__`: the capacity preallocated again (``np.zeros``: pages committed as
        written), the live frames at their ids."""
        state = dict(state)
        live, frames = state.pop("live_ids", None), state.pop("frames")
        self.__dict__.update(state)
        if live is None:  # (a pickle of every frame)
            self.frames = frames
            return
        self.frames = {k: np.zeros((self.capacity, *self.shapes[k]), dtype=v.dtype) for k, v in frames.items()}
        for k, v in frames.items():
            self.frames[k][live] = v

    def copy(self) -> FrameStore:
        """An independent copy of the live frames and the counts (:meth:`__getstate__`)."""
        out = FrameStore.__new__(FrameStore)
        state = self.__getstate__()  # (the frames: copies already)
        out.__setstate__({**state, **{k: v.copy() for k, v in state.items() if isinstance(v, np.ndarray)},
                          "shapes": dict(self.shapes)})
        return out
