"""An actor's collected rows as a batch's arrays, for vector and camera tasks alike (issue 37).

A vector task's observation is a float vector: ``obs`` / ``next_obs`` are the rows stacked. A camera task's is a
Dict of the ``"state"`` vector and its images (:mod:`khgrl.common.tasks.obs_spaces`): ``obs`` / ``next_obs`` are
the state vectors stacked, and the images go as frames, each once (:func:`~khgrl.common.wire.frames.pack_frames`
with ``continues=False``: row 0's observation frame is always sent, see :mod:`khgrl.common.wire.frames`). A camera
stream cuts its batches at :func:`row_limit` rows, so that a batch's frames stay within the wire's limit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from khgrl.common.wire.batch import MAX_BATCH
from khgrl.common.wire.descriptor import STATE
from khgrl.common.wire.frames import max_rows, pack_frames

__all__ = ["state_of", "row_limit", "batch_arrays"]


def state_of(obs: Any) -> Any:
    """The vector a transition's bounds are checked on: a camera observation's ``"state"``, else ``obs``.

    :param obs: one policy observation
    """
    return obs[STATE] if isinstance(obs, dict) else obs


def row_limit(obs: Any) -> int | None:
    """Rows per batch at most for a stream of such observations (None: a vector task, no limit but the run's).

    :param obs: one policy observation
    """
    if not isinstance(obs, dict):
        return None
    cams = tuple((k, tuple(int(d) for d in np.shape(obs[k]))) for k in sorted(obs) if k != STATE)
    return max_rows(cams, MAX_BATCH)


def batch_arrays(obs_rows: list, next_rows: list, done: np.ndarray) -> dict[str, Any]:
    """``obs``, ``next_obs`` (float32) and, for camera observations, ``frames``, ``obs_frame``, ``next_frame``
    (int32) of a batch (:class:`~khgrl.common.wire.batch.Transitions` fields).

    :param obs_rows: per row, the observation
    :param next_rows: per row, the next observation
    :param done: per row, terminated or truncated
    """
    if not isinstance(obs_rows[0], dict):
        return {"obs": np.asarray(obs_rows, dtype=np.float32), "next_obs": np.asarray(next_rows, dtype=np.float32)}
    cams = sorted(k for k in obs_rows[0] if k != STATE)
    images = {k: np.stack([o[k] for o in obs_rows]) for k in cams}
    next_images = {k: np.stack([o[k] for o in next_rows]) for k in cams}
    frames, obs_frame, next_frame = pack_frames(images, next_images, np.asarray(done, dtype=bool), cams,
                                                continues=False)
    return {"obs": np.asarray([o[STATE] for o in obs_rows], dtype=np.float32),
            "next_obs": np.asarray([o[STATE] for o in next_rows], dtype=np.float32), "frames": frames,
            "obs_frame": obs_frame.astype(np.int32), "next_frame": next_frame.astype(np.int32)}
