"""Camera frames in a ``transitions`` batch (issue 37): the batch form, its checks on receipt and its size limits.

A camera task's batch (:class:`~khgrl.common.wire.batch.Transitions`) carries its observations' state vectors in
``obs`` / ``next_obs`` as a vector task's do, and its images apart, each distinct frame once: ``frames`` (camera ->
uint8 (m, H, W, C)) and per row two int32 indices into them, ``obs_frame`` and ``next_frame``. A row that does not
start an episode observes what the row before observed next: ``obs_frame[r] == next_frame[r - 1]``.
:func:`pack_frames` makes this form from per-row observations (the frames in the order a stream produces them: an
episode's first observation, then each row's next observation), so ``m <= n + episode starts + 1``.

``obs_frame[0] == PREV`` would say "row 0's observation is the previous batch's last next observation"; the
learner's :class:`~khgrl.learner.frame_replay.FrameReplayBuffer` takes it. An actor never sends it: it always sends
row 0's observation frame (``continues=False``), so a batch re-sent to a learner that restarted needs nothing that
learner may have lost; the learner stores that frame once all the same (it is pixel-equal to the frame it pinned
for the stream at that step). One extra frame per batch on the wire.

Size: a batch holds at most :func:`max_frames` frames (they take at most :data:`MAX_FRAME_BYTES`, so a batch stays
under the transport's and the journal's limits), and an actor cuts its batches at :func:`max_rows` rows.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from khgrl.common.wire.checks import ProtocolError, unpack_array
from khgrl.common.wire.descriptor import CAMERA_NAME, CHANNELS, MAX_CAMERAS, MAX_SIDE, STATE

__all__ = ["PREV", "MAX_FRAME_BYTES", "Cameras", "pack_frames", "frame_bytes", "max_frames", "max_rows",
           "check_frames", "cameras_of"]

PREV = -1  # ``obs_frame[0]``: the actor stream's last stored next-observation frame (the learner's pin)
MAX_FRAME_BYTES = 56 * 2**20  # the frames of one batch at most (+ 4 MiB of the rest: under the 64 MiB journal body)
Cameras = tuple[tuple[str, tuple[int, int, int]], ...]  # (name, (H, W, C)) per camera, in name order


def frame_bytes(cameras: Cameras) -> int:
    """Bytes of one frame of every camera.

    :param cameras: (name, (H, W, C)) per camera
    """
    return int(sum(h * w * c for _, (h, w, c) in cameras))


def max_frames(cameras: Cameras, max_batch: int) -> int:
    """Frames a batch may carry: two per row of the largest batch, at most :data:`MAX_FRAME_BYTES` of them.

    :param cameras: (name, (H, W, C)) per camera
    :param max_batch: rows of a batch at most
    """
    return max(2, min(2 * max_batch, MAX_FRAME_BYTES // max(1, frame_bytes(cameras))))


def max_rows(cameras: Cameras, max_batch: int) -> int:
    """Rows an actor puts in one batch at most, so that its frames (``m <= 2 n``) fit :func:`max_frames`.

    :param cameras: (name, (H, W, C)) per camera
    :param max_batch: rows of a batch at most
    """
    return max(1, min(max_batch, max_frames(cameras, max_batch) // 2))


def cameras_of(frames: dict[str, np.ndarray]) -> Cameras:
    """The cameras of a batch's ``frames``, in name order.

    :param frames: camera -> (m, H, W, C)
    """
    return tuple((k, tuple(int(d) for d in frames[k].shape[1:])) for k in sorted(frames))


def pack_frames(obs: dict[str, np.ndarray], next_obs: dict[str, np.ndarray], done: np.ndarray,
                cameras: list[str], continues: bool) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The batch form of per-row observations: the distinct frames and each row's ``obs_frame``/``next_frame``
    (int64).

    :param obs: camera -> observations of the rows, shape (n, H, W, C)
    :param next_obs: camera -> next observations, shape (n, H, W, C)
    :param done: per row: terminated or truncated (the next row starts an episode)
    :param cameras: the camera keys to pack
    :param continues: row 0's observation is the previous batch's last next observation (:data:`PREV`)
    """
    n = len(done)
    new_obs = np.ones(n, dtype=bool)  # rows whose observation is a frame of its own: an episode's first
    new_obs[1:] = np.asarray(done[:-1], dtype=bool)
    if n:
        new_obs[0] = not continues
    next_frame = np.cumsum(new_obs.astype(np.int64) + 1) - 1
    obs_frame = np.empty(n, dtype=np.int64)
    obs_frame[new_obs] = next_frame[new_obs] - 1
    cont = np.flatnonzero(~new_obs)
    obs_frame[cont] = np.where(cont > 0, next_frame[np.maximum(cont - 1, 0)], PREV)
    m = int(next_frame[-1]) + 1 if n else 0
    frames = {}
    for k in cameras:
        out = np.empty((m, *next_obs[k].shape[1:]), dtype=next_obs[k].dtype)
        out[next_frame] = next_obs[k]
        out[obs_frame[new_obs]] = obs[k][new_obs]
        frames[k] = out
    return frames, obs_frame, next_frame


def _frames(value: Any, cameras: Cameras | None) -> dict[str, np.ndarray]:
    """The ``frames`` map, checked against the receiver's cameras (None: any, up to the protocol's limits)."""
    if not isinstance(value, dict) or not 1 <= len(value) <= MAX_CAMERAS:
        raise ProtocolError(f"frames: expected a map of 1..{MAX_CAMERAS} cameras")
    want = None if cameras is None else dict(cameras)
    if want is not None and set(value) != set(want):
        raise ProtocolError(f"frames: cameras {sorted(map(str, value))}, expected {sorted(want)}")
    out = {}
    for name in sorted(value, key=str):
        if not isinstance(name, str) or not CAMERA_NAME.match(name) or name == STATE:
            raise ProtocolError(f"frames: camera name {name!r} is not a short identifier other than {STATE!r}")
        shape = (None, None, None, None) if want is None else (None, *want[name])
        arr = unpack_array(value[name], f"frames[{name}]", dtype="|u1", shape=shape)
        h, w, c = arr.shape[1:]
        if not (1 <= h <= MAX_SIDE and 1 <= w <= MAX_SIDE) or c not in CHANNELS:
            raise ProtocolError(f"frames[{name}]: frames of {arr.shape[1:]}: at most {MAX_SIDE} x {MAX_SIDE}, C in "
                                f"{CHANNELS}")
        out[name] = arr
    return out


def _indices(m: dict, name: str, n: int, frames: int) -> np.ndarray:
    arr = unpack_array(m.get(name), name, dtype="<i4", shape=(n,))
    low = np.full(n, 0)
    if name == "obs_frame" and n:
        low[0] = PREV
    bad = np.flatnonzero((arr < low) | (arr >= frames))
    if len(bad):
        r = int(bad[0])
        raise ProtocolError(f"{name}[{r}]: {int(arr[r])} outside [{int(low[r])}, {frames}) (PREV only at row 0)")
    return arr


def check_frames(m: dict, cameras: Cameras | None, n: int, done: np.ndarray,
                 max_batch: int) -> tuple[dict[str, np.ndarray] | None, np.ndarray | None, np.ndarray | None]:
    """A received batch's ``frames``, ``obs_frame`` and ``next_frame`` (the module docstring), all None for a
    batch without images.

    :param m: the batch's map
    :param cameras: the receiver's cameras (its task's; () a vector task: no frames; None: any)
    :param n: the batch's rows
    :param done: per row: terminated or truncated
    :param max_batch: rows of a batch at most
    :raises ProtocolError: naming the field that is wrong
    """
    present = [f for f in ("frames", "obs_frame", "next_frame") if m.get(f) is not None]
    if not present and not cameras:
        return None, None, None
    if cameras == ():
        raise ProtocolError(f"{present[0]}: a batch of a task without cameras has no frames")
    if len(present) < 3:
        missing = next(f for f in ("frames", "obs_frame", "next_frame") if f not in present)
        raise ProtocolError(f"{missing}: missing (a camera task's batch carries frames, obs_frame, next_frame)")
    frames = _frames(m["frames"], cameras)
    counts = {len(a) for a in frames.values()}
    total = counts.pop()
    if counts:
        raise ProtocolError("frames: the cameras hold different numbers of frames")
    starts = int(np.count_nonzero(done[:-1]))
    limit = min(n + starts + 1, max_frames(cameras_of(frames), max_batch))
    if not 1 <= total <= limit:
        raise ProtocolError(f"frames: {total} frames for {n} rows and {starts} episode starts, 1..{limit} allowed")
    obs_frame, next_frame = _indices(m, "obs_frame", n, total), _indices(m, "next_frame", n, total)
    linked = ~np.asarray(done[:-1], dtype=bool)
    broken = np.flatnonzero(linked & (obs_frame[1:] != next_frame[:-1]))
    if len(broken):
        r = int(broken[0]) + 1
        raise ProtocolError(f"obs_frame[{r}]: {int(obs_frame[r])}, but row {r - 1} did not end its episode and "
                            f"observed frame {int(next_frame[r - 1])} next")
    return frames, obs_frame, next_frame
