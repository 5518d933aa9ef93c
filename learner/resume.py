"""A learner's start: a fresh algorithm (``--algo``) and stream table, or both as the newest checkpoint left them
(``--resume``)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery.ingest import StreamTable
from khgrl.learner.algorithm import DEFAULT
from khgrl.learner.checkpoint import fault_reason, load_sound_checkpoint, remove_stale_temps
from khgrl.learner.trainer import Trainer, build_algorithm, keep_freed_memory, torch_device

__all__ = ["open_learner", "rss_mb"]

log = logging.getLogger("khgrl.learner")


def open_learner(tqc: TQCSettings, seed: int, learner_dir: str | Path, *, resume: bool,
                 logger_formats: tuple[str, ...] = ("csv", "tensorboard"), task=None,
                 checkpoint_dir: str | Path | None = None, algo: str = DEFAULT) -> tuple[Trainer, StreamTable]:
    """A fresh model and empty stream table, or (``resume``) both as the newest checkpoint left them. Temporary
    checkpoint directories that killed learners left behind are removed first.

    :param tqc: the run's TQC settings (schedule: ``learning_starts``, ``train_freq``)
    :param seed: the model's seed (a fresh model only)
    :param learner_dir: ``RUN_DIR/learner`` (checkpoint, SB3 logs under ``tb/``)
    :param resume: continue from the checkpoint (:class:`~khgrl.learner.checkpoint.CheckpointError` if there is
        none, or its parameters are not finite: :func:`~khgrl.learner.checkpoint.load_sound_checkpoint`; stored
        transitions out of the task's bounds are dropped)
    :param logger_formats: SB3 logger output formats
    :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: the passage world's spaces)
    :param checkpoint_dir: where the checkpoints are (None: ``learner_dir``)
    :param algo: the learner algorithm's registered name (``--algo``; a checkpoint must be of the same)
    """
    learner_dir = Path(learner_dir)
    learner_dir.mkdir(parents=True, exist_ok=True)
    keep_freed_memory()  # (no page faults in every training iteration)
    ckpt_dir = Path(checkpoint_dir or learner_dir)
    _remove_stale_temps(ckpt_dir)
    kw = dict(learning_starts=tqc.learning_starts, train_freq=tqc.train_freq, log_dir=learner_dir / "tb",
              logger_formats=logger_formats)
    if not resume:
        log.info("learner algorithm %s, seed %d", algo, seed)
        return Trainer(build_algorithm(tqc, seed, task, algo), **kw), StreamTable()
    model, state, ckpt = load_sound_checkpoint(ckpt_dir, task, tqc, torch_device(tqc.device), algo)
    trainer, streams = Trainer(model, **kw), StreamTable.from_state(state)
    trainer.restore(state)
    log.info("%s resumed from %s: %d transitions (buffer pos %d), version %d, %d iterations, actors %s", algo, ckpt,
             trainer.total, trainer.buffer.pos, trainer.version, trainer.iterations,
             {a: streams[a].next_seq for a in streams})
    return trainer, streams


def _remove_stale_temps(ckpt_dir: Path) -> None:
    """Remove the ``checkpoint.tmp-PID`` directories of dead learners (a disk fault is logged, not raised)."""
    try:
        for path in remove_stale_temps(ckpt_dir):
            log.info("removed %s, left by a learner that stopped while saving a checkpoint", path)
    except OSError as exc:
        log.warning("cannot remove leftover temporary checkpoints in %s (%s)", ckpt_dir, fault_reason(exc))


def rss_mb() -> float:
    """This process's resident memory (0 where /proc is not there)."""
    try:
        with open(f"/proc/{os.getpid()}/statm") as fh:
            return round(int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20, 1)
    except (OSError, ValueError, IndexError):
        return 0.0
