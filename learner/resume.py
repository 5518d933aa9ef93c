"""A learner's start: a fresh algorithm (``--algo``) and stream table, or (``--resume``) both as the learner left
them on disk -- the last full checkpoint (model, replay buffer, stream positions), then the journal's batches
after it replayed in order into the replay buffer and the stream table (each row checked, see
:data:`DEFAULT_ROW_CHECK`), then the newest model checkpoint when it fits what was replayed."""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery.ingest import StreamTable
from khgrl.common.wire.bounds import bad_rows
from khgrl.learner.algorithm import DEFAULT, algorithm_class
from khgrl.learner.checkpoint import (
    STATE_FILE,
    CheckpointError,
    find_checkpoint,
    find_model,
    remove_stale_temps,
)
from khgrl.learner.disk_faults import fault_reason
from khgrl.learner.journal import journal_dir, segments
from khgrl.learner.journal_loss import JournalDamage, JournalLoss, check_loss
from khgrl.learner.journal_mark import remove_mark
from khgrl.learner.journal_record import ARRAYS
from khgrl.learner.journal_scan import JournalScan
from khgrl.learner.sound import load_sound_checkpoint
from khgrl.learner.trainer import Trainer, build_algorithm, keep_freed_memory, torch_device

__all__ = ["open_learner", "replay_journal", "rss_mb", "DEFAULT_ROW_CHECK", "JournalDamage"]

log = logging.getLogger("khgrl.learner")

RowCheck = Callable[[dict[str, np.ndarray], Any], np.ndarray]
"""``check(arrays, descriptor) -> bad``: per row of a journal batch (``arrays`` by the names of
:data:`~khgrl.learner.journal_record.ARRAYS`), whether it must not be stored (a boolean array of length n).
``descriptor``: the run's task descriptor (or None)."""

# The check of every journal row a resumed learner replays (another per call through open_learner(row_check=...)).
DEFAULT_ROW_CHECK: RowCheck = bad_rows  # finite, and within the task's value bounds


def open_learner(tqc: TQCSettings, seed: int, learner_dir: str | Path, *, resume: bool,
                 logger_formats: tuple[str, ...] = ("csv", "tensorboard"), task=None,
                 checkpoint_dir: str | Path | None = None, algo: str = DEFAULT,
                 row_check: RowCheck | None = None, accept_journal_loss: bool = False) -> tuple[Trainer, StreamTable]:
    """A fresh model and empty stream table, or (``resume``) both as the learner left them: the last full
    checkpoint, the journal after it, the newest model checkpoint that fits (the module's docstring). Temporary
    checkpoint directories that killed learners left behind are removed first; a fresh start also removes the
    checkpoints and journal of an earlier learner there (a later ``--resume`` must not mix them with this one's).

    :param tqc: the run's TQC settings (schedule: ``learning_starts``, ``train_freq``)
    :param seed: the model's seed (a fresh model; also one resumed from a journal without a full checkpoint)
    :param learner_dir: ``RUN_DIR/learner`` (checkpoint, SB3 logs under ``tb/``)
    :param resume: continue from the checkpoint (:class:`~khgrl.learner.checkpoint.CheckpointError` if there is
        none, or its parameters are not finite: :func:`~khgrl.learner.sound.load_sound_checkpoint`; stored
        transitions out of the task's bounds are dropped)
    :param logger_formats: SB3 logger output formats
    :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: the passage world's spaces)
    :param checkpoint_dir: where the checkpoints are (None: ``learner_dir``)
    :param algo: the learner algorithm's registered name (``--algo``; a checkpoint must be of the same)
    :param row_check: the check of each replayed journal row (None: :data:`DEFAULT_ROW_CHECK`)
    :param accept_journal_loss: resume even if the journal lost confirmed batches (damage): the streams skip
        what is lost (:attr:`StreamTable.journal_loss`); without it such a journal raises :class:`JournalDamage`
        (one line: the file, the byte, the confirmed batches affected) before anything is written
    """
    learner_dir = Path(learner_dir)
    learner_dir.mkdir(parents=True, exist_ok=True)
    keep_freed_memory()  # (no page faults in every training iteration)
    ckpt_dir = Path(checkpoint_dir or learner_dir)
    _remove_stale_temps(ckpt_dir)
    kw = dict(learning_starts=tqc.learning_starts, train_freq=tqc.train_freq, log_dir=learner_dir / "tb",
              logger_formats=logger_formats, reward_bound=None if task is None else task.reward_bound)
    if not resume:
        _remove_earlier(ckpt_dir)
        log.info("learner algorithm %s, seed %d", algo, seed)
        return Trainer(build_algorithm(tqc, seed, task, algo), **kw), StreamTable()
    ckpt, jdir = find_checkpoint(ckpt_dir), journal_dir(ckpt_dir)
    device = torch_device(tqc.device)
    if ckpt is not None:
        model, state, ckpt = load_sound_checkpoint(ckpt_dir, task, tqc, device, algo)  # (finite, rows in bounds)
        trainer, streams = Trainer(model, **kw), StreamTable.from_state(state)
        trainer.restore(state)
        start = state["journal"]["next"] if isinstance(state.get("journal"), dict) else None
    elif segments(jdir):
        log.info("no full checkpoint under %s: a fresh model (seed %d) and the whole journal", ckpt_dir, seed)
        trainer, streams, start = Trainer(build_algorithm(tqc, seed, task, algo), **kw), StreamTable(), 0
    else:
        raise CheckpointError(f"--resume: no checkpoint under {ckpt_dir}")
    base = trainer.total
    streams.journal_loss = None
    if start is not None:
        loss = JournalLoss()
        replay_journal(trainer, streams, jdir, int(start), row_check or DEFAULT_ROW_CHECK, task, loss=loss)
        check_loss(loss, accept_journal_loss)
        streams.journal_loss = loss if loss else None
        streams.mark_durable()  # everything replayed is on disk
    streams.skipped = 0  # (batches lost from here on are counted)
    _adopt_model(trainer, ckpt_dir, base, task, tqc, device, algo, kw)
    log.info("%s resumed from %s: %d transitions (buffer pos %d), version %d, %d iterations, actors %s", algo,
             ckpt or jdir, trainer.total, trainer.buffer.pos, trainer.version, trainer.iterations,
             {a: streams[a].next_seq for a in streams})
    return trainer, streams


def replay_journal(trainer: Trainer, streams: StreamTable, directory: Path, start: int, row_check: RowCheck,
                   task: Any = None, loss: JournalLoss | None = None) -> tuple[int, int]:
    """Store the journal's batches from segment ``start`` on, in order, as the ingest thread stored them (their
    actors' streams advance as they did). A batch with a bad row (``row_check``) is not stored, but its seq is
    taken (its actor does not send it again); a duplicate is logged; a gap in front of a batch (batches the journal
    lost: damage) is stepped over and noted in ``loss``, with the damage the scan found. Returns the batches stored
    and dropped.

    :param trainer: the trainer (its replay buffer and schedule)
    :param streams: the stream table (from the full checkpoint, or empty)
    :param directory: the journal directory
    :param start: the first segment to replay (the full checkpoint's ``journal.next``)
    :param row_check: per row of a batch, whether it is bad
    :param task: the run's task descriptor (for ``row_check``)
    :param loss: where the damage and the gaps go (None: not kept)
    """
    stored = dropped = rows = 0
    loss = loss if loss is not None else JournalLoss()
    scan = JournalScan(directory, start)
    for rec in scan.records():
        msg = rec.msg
        loss.step_over_gap(streams, rec)
        res = streams.offer(msg)
        if res.result != "accepted":
            log.warning("journal: batch %d of actor %s (stream %s) is %s on replay", msg.envelope.seq, msg.actor,
                        msg.stream, res.result)
            continue
        for batch in res.ready:
            bad = np.asarray(row_check({name: getattr(batch, name) for name, _, _ in ARRAYS}, task), dtype=bool)
            if bad.any():
                dropped += 1
                res.stream.index = batch.first_step + batch.n
                log.warning("journal: batch %d of actor %s has %d bad rows (of %d): not stored", batch.envelope.seq,
                            batch.actor, int(bad.sum()), batch.n)
                continue
            trainer.add(batch, res.stream, streams.positions)
            res.stream.mark()  # (as the ingest thread marks it: trained weights cover it, then it leaves the lead)
            stored += 1
            rows += batch.n
    loss.finish(scan, streams)
    if stored or dropped:
        log.info("journal: replayed %d batches (%d transitions) from segment %d on; %d dropped", stored, rows, start,
                 dropped)
    return stored, dropped


def _adopt_model(trainer: Trainer, ckpt_dir: Path, base: int, task: Any, tqc: TQCSettings, device: str, algo: str,
                 kw: dict) -> None:
    """Continue from the model checkpoint if it is newer than the full checkpoint's model and covers no more
    data than the replay holds (it was saved after the journal was synced): its networks, optimisers and
    counters; the iterations it had not trained yet plus those the replay brought later stay due."""
    found = find_model(ckpt_dir)
    if found is None:
        return
    try:
        m = json.loads((found / STATE_FILE).read_text())
        total, iterations = int(m["total_ingested"]), int(m["iterations"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("model checkpoint %s unreadable (%s): not used", found, exc)
        return
    if m.get("algo", DEFAULT) != algo or iterations <= trainer.iterations or not base <= total <= trainer.total:
        log.info("model checkpoint %s (%d transitions, %d iterations) not used: the full checkpoint and journal give "
                 "%d transitions, %d iterations", found, total, iterations, trainer.total, trainer.iterations)
        return
    try:
        model = algorithm_class(algo).load(found, task, tqc, device, buffer=trainer.buffer)
    except (ValueError, OSError) as exc:
        log.warning("model checkpoint %s does not load (%s): not used", found, exc)
        return
    if model.fault() is not None:
        log.error("model checkpoint %s: %s is not finite (NaN or inf): not used", found, model.fault())
        return
    model.set_logger(Path(kw["log_dir"]), kw["logger_formats"])
    later = [[at, snap] for at, snap in trainer.due if at > total]
    trainer.algo = model
    trainer.restore({**m, "total_ingested": trainer.total, "due": [*m["due"], *later]})
    log.info("model checkpoint %s: version %d, %d iterations", found, trainer.version, trainer.iterations)


def _remove_earlier(ckpt_dir: Path) -> None:
    """A fresh start: remove an earlier learner's checkpoints and journal from ``ckpt_dir`` (logged)."""
    for name in ("checkpoint", "checkpoint.old", "model", "model.old"):
        path = ckpt_dir / name
        if path.is_dir():
            log.warning("fresh start (no --resume): removing the earlier learner's %s", path)
            shutil.rmtree(path, ignore_errors=True)
    for _, path in segments(journal_dir(ckpt_dir)):
        path.unlink(missing_ok=True)
    remove_mark(journal_dir(ckpt_dir))


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
