"""Learner checkpoints on local disk under ``CHECKPOINT_DIR`` (``RUN_DIR/learner`` unless ``--checkpoint-dir``
puts it elsewhere, e.g. on a data disk).

Durability has three parts (the learner loop schedules them, :mod:`khgrl.learner.loop`):

* the **journal** (:mod:`khgrl.learner.journal`, ``journal/``): every batch stored, appended and fsynced in groups;
  what makes an actor's batch durable (``durable`` in its acks) moments after it arrived;
* the **model checkpoint** (:func:`save_model`, ``model/``): ``model.zip`` and ``state.json`` without the replay
  buffer, every ``--model-checkpoint-every`` training iterations (after the journal is synced, so it never covers
  data the journal does not hold);
* the **full checkpoint** (:func:`save_checkpoint`, ``checkpoint/``), rare: what the learner algorithm saves
  (:meth:`~khgrl.learner.algorithm.LearnerAlgorithm.save`: ``model.zip``, policy, optimisers, entropy
  coefficient; ``replay_buffer.pkl``, SB3's pickle of the :class:`~khgrl.learner.replay.StreamReplayBuffer`:
  transitions with their intervention and clip flags and provenance) and ``state.json`` (the algorithm's name,
  stream positions, counters, pending training iterations, weights version, and ``journal.next``: the first
  journal segment after it). Written when the journal holds a replay buffer's worth since the last one (or every
  ``--checkpoint-every``), after a failed journal write, and at the end; the journal segments before it are then
  deleted. With a working journal, ingest pauses only while the journal is cut and the buffer copied
  (:func:`copy_buffer`); the copy is saved meanwhile.

A resumed learner (:mod:`khgrl.learner.resume`) loads the full checkpoint, replays the journal after it, and takes
the model checkpoint when it is newer. A checkpoint is resumed by the algorithm that wrote it (one without a name:
``tqc``). Each is written to a temporary directory (``checkpoint.tmp-PID`` / ``model.tmp-PID``, fsynced) that is
then renamed into place, ``state.json`` last, so a crash leaves either the previous checkpoint or the new one,
never a mix. The pickle is our own file on local disk, never anything from the wire. (SB3 is imported when a
checkpoint is read, so that finding one is cheap.)

A resumed learner checks what it loads (:func:`~khgrl.learner.sound.load_sound_checkpoint`): a NaN or infinite
parameter refuses the checkpoint (the learner falls back to ``checkpoint.old`` when a cut-short save left one, else
exits 2 naming the file), and stored transitions that are not finite or lie outside the task's value bounds are
dropped (logged with counts).

Disk faults (a full, read-only or unwritable directory): a failed save removes its temporary directory and
leaves the previous checkpoint as it was; :mod:`khgrl.learner.disk_faults` says which errors are the disk's, and
counts, logs and schedules the retries. A learner started anew removes the temporary directories that killed
learners left behind (:func:`remove_stale_temps`).

One module of ~300 lines on purpose: writing and reading one checkpoint format (atomic swap, fsync, stale
temporaries) must stay in one place so that both sides agree.
"""

from __future__ import annotations

import copy
import errno
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from khgrl.learner.algorithm import BUFFER_FILE, DEFAULT, MODEL_FILE, algorithm_class

__all__ = ["STATE_FILE", "MODEL_FILE", "BUFFER_FILE", "FORMAT", "TMP_PREFIX", "MODEL_TMP_PREFIX", "CheckpointError",
           "checkpoint_dir", "model_dir", "can_resume", "copy_buffer", "find_checkpoint", "find_model", "newest_model",
           "save_checkpoint", "save_model", "load_checkpoint", "load_checkpoint_arrays", "remove_stale_temps"]

log = logging.getLogger("khgrl.learner")

STATE_FILE = "state.json"
TMP_PREFIX = "checkpoint.tmp-"  # + the PID of the learner writing it
MODEL_TMP_PREFIX = "model.tmp-"  # (the model checkpoint's)
FORMAT = 2  # 1: side arrays in .npy files beside the buffer; 2: inside the replay buffer pickle


class CheckpointError(RuntimeError):
    """A checkpoint that is missing or cannot be resumed."""


def checkpoint_dir(learner_dir: str | Path) -> Path:
    """Where the learner of ``learner_dir`` (``RUN_DIR/learner``, or its ``--checkpoint-dir``) keeps its checkpoint.

    :param learner_dir: the learner's checkpoint directory
    """
    return Path(learner_dir) / "checkpoint"


def model_dir(learner_dir: str | Path) -> Path:
    """Where the learner of ``learner_dir`` keeps its model checkpoint (``model.zip`` and ``state.json``, no
    replay buffer).

    :param learner_dir: the learner's checkpoint directory
    """
    return Path(learner_dir) / "model"


def _old_dir(learner_dir: str | Path, name: str = "checkpoint") -> Path:
    return Path(learner_dir) / f"{name}.old"


def find_checkpoint(learner_dir: str | Path) -> Path | None:
    """The newest complete checkpoint under ``learner_dir`` (``checkpoint/``, else the ``checkpoint.old/`` a
    crash during the rename left behind), or None.

    :param learner_dir: the learner's checkpoint directory (``RUN_DIR/learner`` or its ``--checkpoint-dir``)
    """
    for d in (checkpoint_dir(learner_dir), _old_dir(learner_dir)):
        if (d / STATE_FILE).is_file():
            return d
    return None


def can_resume(learner_dir: str | Path) -> bool:
    """Whether a learner can be resumed from ``learner_dir``: a full checkpoint or a journal segment is there.

    :param learner_dir: the learner's checkpoint directory
    """
    return find_checkpoint(learner_dir) is not None or any((Path(learner_dir) / "journal").glob("segment-*.bin"))


def find_model(learner_dir: str | Path) -> Path | None:
    """The newest complete model checkpoint under ``learner_dir`` (``model/``, else ``model.old/``), or None.

    :param learner_dir: the learner's checkpoint directory
    """
    for d in (model_dir(learner_dir), _old_dir(learner_dir, "model")):
        if (d / STATE_FILE).is_file() and (d / MODEL_FILE).is_file():
            return d
    return None


def newest_model(learner_dir: str | Path) -> Path | None:
    """The directory of the most trained model under ``learner_dir``: the full checkpoint or the model checkpoint,
    whichever ``state.json`` counts more training iterations in (None: neither).

    :param learner_dir: the learner's checkpoint directory
    """
    best, most = None, -1
    for found in (find_checkpoint(learner_dir), find_model(learner_dir)):
        if found is None or not (found / MODEL_FILE).is_file():
            continue
        try:
            iterations = int(json.loads((found / STATE_FILE).read_text()).get("iterations", 0))
        except (OSError, ValueError, TypeError):
            continue
        if iterations > most:
            best, most = found, iterations
    return best


def _fsync(path: Path, directory: bool = False) -> None:
    """Flush a file (or a directory's entries) to the disk; a filesystem that cannot fsync a directory is let be."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as exc:
        if not directory or exc.errno not in (errno.EINVAL, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def copy_buffer(buffer: Any) -> Any:
    """A copy of a replay buffer (its arrays copied, under its lock) to save while the live one takes more.

    :param buffer: the :class:`~khgrl.learner.replay.StreamReplayBuffer`
    """
    with buffer.lock:
        out = copy.copy(buffer)
        for name, value in vars(buffer).items():
            if isinstance(value, np.ndarray):
                setattr(out, name, value.copy())
    return out


def _write(tmp: Path, algo: Any, state: dict[str, Any], buffer: Any = True) -> None:
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    for path in (algo.save(tmp) if buffer is True else algo.save(tmp, buffer=buffer)):
        _fsync(path)
    with open(tmp / STATE_FILE, "w") as fh:  # written last: a checkpoint without it is incomplete
        json.dump({"format": FORMAT, "time": time.time(), **state}, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())


def _swap_in(learner_dir: Path, tmp: Path, name: str = "checkpoint") -> Path:
    """Rename ``tmp`` to ``NAME/``; the previous one is ``NAME.old/`` until the new one is in place."""
    final, old = learner_dir / name, _old_dir(learner_dir, name)
    if final.exists():
        if old.exists():
            shutil.rmtree(old)
        os.rename(final, old)
    os.rename(tmp, final)  # (with no checkpoint/ but a checkpoint.old/, that one is kept until here)
    _fsync(learner_dir, directory=True)
    shutil.rmtree(old, ignore_errors=True)
    return final


def save_checkpoint(learner_dir: str | Path, algo: Any, state: dict[str, Any], buffer: Any = None) -> Path:
    """Write model, replay buffer and ``state`` to a temporary directory, then rename it to ``checkpoint/``
    (the previous checkpoint is kept until then). On any error the temporary directory is removed, the previous
    checkpoint is left as it was, and the error is raised (:func:`is_disk_fault` tells a disk fault).

    :param learner_dir: the learner's checkpoint directory (``RUN_DIR/learner`` or its ``--checkpoint-dir``)
    :param algo: the learner algorithm (:class:`~khgrl.learner.algorithm.LearnerAlgorithm`; its replay buffer is
        saved with it)
    :param state: JSON-able counters and stream positions (``format`` and ``time`` are added)
    :param buffer: the replay buffer to save (a :func:`copy_buffer` taken with ``state``; None: the algorithm's)
    """
    return _save(Path(learner_dir), algo, state, "checkpoint", TMP_PREFIX, buffer=True if buffer is None else buffer)


def save_model(learner_dir: str | Path, algo: Any, state: dict[str, Any]) -> Path:
    """The model checkpoint: ``model.zip`` and ``state`` (no replay buffer: the last full checkpoint and the
    journal hold the data), written like :func:`save_checkpoint` to ``model/``.

    :param learner_dir: the learner's checkpoint directory
    :param algo: the learner algorithm
    :param state: JSON-able counters (the trainer's state)
    """
    return _save(Path(learner_dir), algo, state, "model", MODEL_TMP_PREFIX, buffer=False)


def _save(learner_dir: Path, algo: Any, state: dict[str, Any], name: str, prefix: str, buffer: Any) -> Path:
    tmp = learner_dir / f"{prefix}{os.getpid()}"
    try:
        _write(tmp, algo, state, buffer)
        return _swap_in(learner_dir, tmp, name)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(learner_dir: str | Path) -> list[Path]:
    """Remove the ``checkpoint.tmp-PID`` directories of learners that died while saving (they can hold as much
    as a whole checkpoint); one of a PID still running other than this process is left alone. Never touches
    ``checkpoint/`` or ``checkpoint.old/``. Returns what was removed; raises :class:`OSError` if one cannot be.

    :param learner_dir: the learner's checkpoint directory
    """
    removed: list[Path] = []
    directory = Path(learner_dir)
    if not directory.is_dir():
        return removed
    for path in sorted([*directory.glob(TMP_PREFIX + "*"), *directory.glob(MODEL_TMP_PREFIX + "*")]):
        pid = path.name.rpartition("-")[2]
        if pid.isdigit() and int(pid) != os.getpid() and _pid_alive(int(pid)):
            log.warning("left %s alone: process %s is running", path, pid)
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
        removed.append(path)
    return removed


def load_checkpoint(ckpt: str | Path, task: Any, settings: Any, device: str = "cpu",
                    algo: str = DEFAULT) -> tuple[Any, dict[str, Any]]:
    """The learner algorithm (with its replay buffer) and the state of a checkpoint.

    :param ckpt: the checkpoint directory (:func:`find_checkpoint`)
    :param task: the run's task descriptor (the model's spaces; None: the passage world)
    :param settings: the run's learner settings (``TQCSettings``)
    :param device: the torch device to train on (a checkpoint made on a GPU resumes on a CPU and back)
    :param algo: the run's ``--algo``; a checkpoint of another algorithm is refused
    """
    ckpt = Path(ckpt)
    state = json.loads((ckpt / STATE_FILE).read_text())
    if state.get("format", 1) != FORMAT:
        raise CheckpointError(f"{ckpt}: checkpoint format {state.get('format', 1)} was written by an older learner "
                              f"and cannot be resumed by this one (format {FORMAT})")
    saved = state.get("algo", DEFAULT)
    if saved != algo:
        raise CheckpointError(f"{ckpt}: a checkpoint of a {saved} learner; this run's --algo is {algo}")
    try:
        return algorithm_class(algo).load(ckpt, task, settings, device), state
    except ValueError as exc:
        raise CheckpointError(f"{ckpt}: {exc}") from None


def load_checkpoint_arrays(ckpt: str | Path) -> dict[str, np.ndarray]:
    """The per-replay-slot arrays of a checkpoint: ``provenance_actor``, ``provenance_step``, ``intervened``
    and ``clipped`` (whole buffer; empty slots have provenance -1). Reads the saved replay buffer (or the
    ``.npy`` files of a format-1 checkpoint).

    :param ckpt: the checkpoint directory
    """
    from khgrl.learner.replay import SIDE_ARRAYS, StreamReplayBuffer
    from stable_baselines3.common.save_util import load_from_pkl

    ckpt = Path(ckpt)
    if all((ckpt / f"{name}.npy").is_file() for name in SIDE_ARRAYS):  # format 1
        return {name: np.load(ckpt / f"{name}.npy", allow_pickle=False) for name in SIDE_ARRAYS}
    buffer = load_from_pkl(ckpt / BUFFER_FILE)
    if not isinstance(buffer, StreamReplayBuffer):
        raise CheckpointError(f"{ckpt}: the replay buffer has no per-slot arrays ({type(buffer).__name__})")
    return {name: np.array(arr, copy=True) for name, arr in buffer.side_arrays().items()}
