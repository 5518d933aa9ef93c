"""Learner checkpoints on local disk: ``RUN_DIR/learner/checkpoint/``.

A checkpoint holds ``model.zip`` (policy, optimisers, entropy coefficient), ``replay_buffer.pkl`` (SB3's
pickle of the :class:`~learner.replay.StreamReplayBuffer`: transitions with their intervention and clip flags
and provenance) and ``state.json`` (stream positions, counters, pending training iterations, weights version).
It is written to a temporary directory that is then renamed into place, ``state.json`` last, so a crash
leaves either the previous checkpoint or the new one, never a mix. The pickle is our own file on local disk,
never anything from the wire. (SB3 is imported when a checkpoint is read, so that finding one is cheap.)
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["STATE_FILE", "FORMAT", "CheckpointError", "checkpoint_dir", "find_checkpoint", "save_checkpoint",
           "load_checkpoint", "load_checkpoint_arrays"]

STATE_FILE = "state.json"
MODEL_FILE = "model.zip"
BUFFER_FILE = "replay_buffer.pkl"
FORMAT = 2  # 1: side arrays in .npy files beside the buffer; 2: inside the replay buffer pickle


class CheckpointError(RuntimeError):
    """A checkpoint that is missing or cannot be resumed."""


def checkpoint_dir(learner_dir: str | Path) -> Path:
    """Where the learner of ``learner_dir`` (``RUN_DIR/learner``) keeps its checkpoint.

    :param learner_dir: the learner's directory
    """
    return Path(learner_dir) / "checkpoint"


def _old_dir(learner_dir: str | Path) -> Path:
    return Path(learner_dir) / "checkpoint.old"


def find_checkpoint(learner_dir: str | Path) -> Path | None:
    """The newest complete checkpoint under ``learner_dir`` (``checkpoint/``, else the ``checkpoint.old/`` a
    crash during the rename left behind), or None.

    :param learner_dir: the learner's directory (``RUN_DIR/learner``)
    """
    for d in (checkpoint_dir(learner_dir), _old_dir(learner_dir)):
        if (d / STATE_FILE).is_file():
            return d
    return None


def save_checkpoint(learner_dir: str | Path, model: Any, state: dict[str, Any]) -> Path:
    """Write model, replay buffer and ``state`` to a temporary directory, then rename it to ``checkpoint/``
    (the previous checkpoint is kept until then).

    :param learner_dir: the learner's directory (``RUN_DIR/learner``)
    :param model: the TQC model (its replay buffer is saved with it)
    :param state: JSON-able counters and stream positions (``format`` and ``time`` are added)
    """
    learner_dir = Path(learner_dir)
    tmp = learner_dir / f"checkpoint.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    model.save(tmp / MODEL_FILE)
    model.save_replay_buffer(tmp / BUFFER_FILE)
    with open(tmp / STATE_FILE, "w") as fh:  # written last: a checkpoint without it is incomplete
        json.dump({"format": FORMAT, "time": time.time(), **state}, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    final, old = checkpoint_dir(learner_dir), _old_dir(learner_dir)
    if old.exists():
        shutil.rmtree(old)
    if final.exists():
        os.rename(final, old)
    os.rename(tmp, final)
    if old.exists():
        shutil.rmtree(old)
    return final


def load_checkpoint(ckpt: str | Path, env: Any) -> tuple[Any, dict[str, Any]]:
    """The model (with its replay buffer) and the state of a checkpoint.

    :param ckpt: the checkpoint directory (:func:`find_checkpoint`)
    :param env: an environment with the model's spaces (``common.spaces.SpacesEnv``)
    """
    from sb3_contrib import TQC

    from learner.replay import StreamReplayBuffer

    ckpt = Path(ckpt)
    state = json.loads((ckpt / STATE_FILE).read_text())
    if state.get("format", 1) != FORMAT:
        raise CheckpointError(f"{ckpt}: checkpoint format {state.get('format', 1)} was written by an older learner "
                              f"and cannot be resumed by this one (format {FORMAT})")
    model = TQC.load(ckpt / MODEL_FILE, env=env, device="cpu")
    model.load_replay_buffer(ckpt / BUFFER_FILE)
    if not isinstance(model.replay_buffer, StreamReplayBuffer):
        raise CheckpointError(f"{ckpt}: the replay buffer is a {type(model.replay_buffer).__name__}, "
                              "not a StreamReplayBuffer")
    return model, state


def load_checkpoint_arrays(ckpt: str | Path) -> dict[str, np.ndarray]:
    """The per-replay-slot arrays of a checkpoint: ``provenance_actor``, ``provenance_step``, ``intervened``
    and ``clipped`` (whole buffer; empty slots have provenance -1). Reads the saved replay buffer (or the
    ``.npy`` files of a format-1 checkpoint).

    :param ckpt: the checkpoint directory
    """
    from stable_baselines3.common.save_util import load_from_pkl

    from learner.replay import SIDE_ARRAYS, StreamReplayBuffer

    ckpt = Path(ckpt)
    if all((ckpt / f"{name}.npy").is_file() for name in SIDE_ARRAYS):  # format 1
        return {name: np.load(ckpt / f"{name}.npy", allow_pickle=False) for name in SIDE_ARRAYS}
    buffer = load_from_pkl(ckpt / BUFFER_FILE)
    if not isinstance(buffer, StreamReplayBuffer):
        raise CheckpointError(f"{ckpt}: the replay buffer has no per-slot arrays ({type(buffer).__name__})")
    return {name: np.array(arr, copy=True) for name, arr in buffer.side_arrays().items()}
