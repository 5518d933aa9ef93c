"""What a resumed learner refuses to resume from: a checkpoint whose parameters are not finite (NaN or inf), and
stored transitions that are not finite or lie outside the task's value bounds (issue 21: a poisoned checkpoint made
every resume crash). :func:`load_sound_checkpoint` loads the newest checkpoint that passes, :func:`drop_bad_rows`
removes the bad rows from a replay buffer.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from khgrl.learner.algorithm import BUFFER_FILE, DEFAULT, MODEL_FILE
from khgrl.learner.checkpoint import STATE_FILE, CheckpointError, _old_dir, find_checkpoint, load_checkpoint

__all__ = ["load_sound_checkpoint", "drop_bad_rows"]

log = logging.getLogger("khgrl.learner")


def load_sound_checkpoint(learner_dir: str | Path, task: Any, settings: Any, device: str = "cpu",
                          algo: str = DEFAULT) -> tuple[Any, dict[str, Any], Path]:
    """The newest checkpoint whose parameters are all finite (:func:`load_checkpoint`), with the stored transitions
    that are not finite or lie outside the task's bounds dropped from its replay buffer (:func:`drop_bad_rows`,
    logged with counts). A checkpoint with a NaN or infinite parameter is refused; the learner falls back to
    ``checkpoint.old`` where a save was cut short after the new one was in place (that one holds everything the
    acks called durable: they follow the rename), else it raises.

    :param learner_dir: the learner's checkpoint directory (``RUN_DIR/learner`` or its ``--checkpoint-dir``)
    :param task: the run's task descriptor (spaces, value bounds; None: the passage world, finiteness only)
    :param settings: the run's learner settings
    :param device: the torch device to train on
    :param algo: the run's ``--algo``
    :raises CheckpointError: no checkpoint, or none with finite parameters (naming the file and the parameter)
    """
    ckpt = find_checkpoint(learner_dir)
    if ckpt is None:
        raise CheckpointError(f"--resume: no checkpoint under {learner_dir}")
    model, state = load_checkpoint(ckpt, task, settings, device, algo)
    fault = model.fault()
    if fault is not None:
        refused = (f"{ckpt / MODEL_FILE}: {fault} is not finite (NaN or inf): a learner does not resume from it "
                   f"(move {ckpt} away to start the learner afresh)")
        old = _old_dir(learner_dir)
        if ckpt == old or not (old / STATE_FILE).is_file():
            raise CheckpointError(refused)
        log.error("%s; trying the previous checkpoint %s", refused, old)
        try:
            model, state = load_checkpoint(old, task, settings, device, algo)
        except Exception as exc:  # noqa: BLE001 - a half-removed old checkpoint: the first refusal is the error
            raise CheckpointError(f"{refused}; the previous one, {old}, does not load either ({exc})") from None
        if model.fault() is not None:
            raise CheckpointError(f"{refused}; the previous one, {old}, is not finite either ({model.fault()})")
        ckpt = old
    dropped = drop_bad_rows(model.buffer, task)
    if dropped:
        log.warning("%s: dropped %d of the stored transitions (by actor code: %s): a value not finite or outside the "
                    "task's bounds (%d kept)", ckpt / BUFFER_FILE, sum(dropped.values()), dropped,
                    model.buffer.pos)
    return model, state, ckpt


_BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def drop_bad_rows(buffer: Any, task: Any) -> dict[int, int]:
    """Remove the stored transitions :func:`~khgrl.common.wire.bounds.bad_rows` flags from a replay buffer: the
    others move to its front in their order (oldest first), the buffer is then not full, its position after them
    and the freed slots empty (provenance -1). Returns the transitions dropped per provenance code (empty: none).

    :param buffer: a :class:`~khgrl.learner.replay.StreamReplayBuffer` (a
        :class:`~khgrl.learner.frame_replay.FrameReplayBuffer`: its slots' frame ids move too, its frame store's counts
        are rebuilt; the state vectors are what is checked)
    :param task: the run's task descriptor (None: finiteness and +-1e12 only)
    """
    from khgrl.common.wire.bounds import bad_rows

    size = buffer.buffer_size if buffer.full else buffer.pos
    if size == 0:
        return {}
    with buffer.lock:
        bad = bad_rows({"obs": buffer.observations[:size], "next_obs": buffer.next_observations[:size],
                        "action": buffer.actions[:size], "reward": buffer.rewards[:size]}, task)
        if not bad.any():
            return {}
        codes, counts = np.unique(buffer.provenance_actor[:size][bad], return_counts=True)
        order = np.arange(size) if not buffer.full else np.roll(np.arange(size), -buffer.pos)  # oldest first
        keep = order[~bad[order]]
        arrays = [getattr(buffer, name) for name in _BUFFER_ARRAYS] + list(buffer.side_arrays().values())
        frame_ids = list(buffer.frame_arrays().values()) if hasattr(buffer, "frame_arrays") else []
        for arr in arrays + frame_ids:
            arr[:len(keep)] = arr[keep]
            empty = arr is buffer.provenance_actor or arr is buffer.provenance_step or any(arr is f for f in frame_ids)
            arr[len(keep):] = -1 if empty else 0
        buffer.pos, buffer.full = len(keep), False
        if frame_ids:  # a FrameReplayBuffer: the dropped slots' frames freed (those the kept slots and pins hold kept)
            buffer.recount()
    return {int(c): int(n) for c, n in zip(codes, counts)}
