"""The learner's durability (:mod:`khgrl.learner.checkpoint` describes the parts): what the learner loop calls to
journal stored batches, sync the journal, save the model and the full checkpoint on their schedules, and ack the
actors with what is now durable.

With a :class:`~khgrl.learner.journal.Journal` (the default) every batch stored is also appended to the journal;
the *journal thread* (:meth:`Durability.sync_loop`) writes and fsyncs what waits as one group and acks its actors
with the new ``durable`` (the highest seq on disk). The model is saved on its own schedule (``model_every``
training iterations: ``model/``, small); the full checkpoint -- model and whole replay buffer, ``checkpoint/`` --
is rare: when the journal since the last one holds a replay buffer's worth of transitions (or every
``checkpoint_every``), when the journal failed (disk fault: the checkpoint holds what the journal missed), and at
the end; the journal's older segments are then deleted. An actor's ``checkpoint`` request syncs the journal and
saves the model. Without a journal, full checkpoints alone make batches durable (every ``checkpoint_every``, on
request, at the end).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

from khgrl.common.delivery.ingest import StreamTable
from khgrl.learner.checkpoint import copy_buffer, save_checkpoint, save_model
from khgrl.learner.disk_faults import SaveFaults, is_disk_fault
from khgrl.learner.journal import Journal
from khgrl.learner.trainer import Trainer

__all__ = ["Durability"]

log = logging.getLogger("khgrl.learner")

IDLE_WAIT_S = 0.05  # how long the journal thread waits for something to write before looking at the stop flag


class Durability:
    """Journal, model checkpoints and full checkpoints of one learner incarnation.

    :param trainer: the model, its replay buffer and schedule
    :param streams: the actor streams
    :param ckpt_dir: the learner's checkpoint directory
    :param checkpoint_every: a full checkpoint every N ingested transitions (0: the journal's schedule; without a
        journal, only when asked and at the end)
    :param clock: monotonic seconds (retries)
    :param journal: the journal of stored batches (None: only full checkpoints make batches durable)
    :param model_every: with a journal, save the model every N training iterations (0: only in full checkpoints)
    :param snapshot_rows: with a journal, a full checkpoint once it holds this many transitions since the last
        one (None: the replay buffer's size)
    """

    def __init__(self, trainer: Trainer, streams: StreamTable, ckpt_dir: Path, *, checkpoint_every: int,
                 clock: Callable[[], float], journal: Journal | None, model_every: int,
                 snapshot_rows: int | None) -> None:
        self.trainer, self.streams, self.ckpt_dir = trainer, streams, Path(ckpt_dir)
        self.saves = SaveFaults(clock)  # failed saves and journal writes (disk faults) and their retry backoff
        self.checkpoint_every = int(checkpoint_every)
        self.journal = journal
        self.model_every = int(model_every) if journal is not None else 0
        self.snapshot_rows = int(snapshot_rows or trainer.buffer.buffer_size)
        self.checkpoint_requested = False
        self.checkpoints = 0
        self.model_checkpoints = 0
        self.last_ckpt_total = trainer.total
        self.last_model_iterations = trainer.iterations
        self.ingest: Any = None  # the learner's LearnerIngest (its lock, acks): set by the loop

    @property
    def lock(self) -> Any:
        """The ingest lock (streams, counters, acks)."""
        return self.ingest.lock

    def store(self, batch: Any, stream: Any, positions: Callable[[], dict[str, int]]) -> None:
        """Store an accepted batch (ingest thread, :attr:`lock` held) and journal it."""
        self.trainer.add(batch, stream, positions)
        if self.journal is not None:
            self.journal.append(batch, stream)

    def work(self) -> None:
        """A full checkpoint when due (see the module), else what a request asks (journal: sync it and save the
        model), else the model checkpoint when due; after a failed save, only once its retry is due."""
        tr, j, every = self.trainer, self.journal, self.checkpoint_every
        full = (every > 0 and tr.total - self.last_ckpt_total >= every) or (j is None and self.checkpoint_requested) \
            or (j is not None and (bool(j.error) or j.rows >= self.snapshot_rows))
        if full:
            if self.saves.ready():
                self.checkpoint_requested = False
                self.checkpoint()
            return
        if self.checkpoint_requested:
            self.checkpoint_requested = False
            self.sync_journal()
            if tr.iterations > self.last_model_iterations and self.saves.ready():
                self.save_model()
            self.ingest.ack_all()
        elif self.model_every and tr.iterations - self.last_model_iterations >= self.model_every and \
                self.saves.ready():
            self.save_model()

    def not_durable(self) -> int:
        """Transitions stored that neither the last full checkpoint nor the journal (on disk) holds."""
        synced = self.journal.synced_rows if self.journal is not None else 0
        return max(0, self.trainer.total - self.last_ckpt_total - synced)

    def sync_journal(self) -> None:
        """Write and fsync what waits in the journal, raise ``durable`` of those streams and ack their actors; a
        failed write is a disk fault (logged, shown in the status; a full checkpoint comes due)."""
        if self.journal is None:
            return
        marks, exc = self.journal.sync()
        if not marks and exc is None:
            return
        with self.lock:
            self._durable(marks)
            if exc is not None:
                self.saves.failed(exc, self.not_durable(), "journal write")

    def _durable(self, marks: dict) -> None:
        """Streams whose batches up to a seq are on disk (call with :attr:`lock` held): raise and ack."""
        for stream, seq in marks.values():
            if seq > stream.durable:
                stream.durable = seq
            if stream.actor in self.streams and self.streams[stream.actor] is stream:
                self.ingest.pub.ack(self.ingest.ack(stream.actor))

    def save_model(self) -> Path | None:
        """Save the model checkpoint (``model/``: model and counters, no replay buffer) after syncing the journal,
        so that it never covers data the journal does not hold. A disk fault is logged and retried (None)."""
        tr = self.trainer
        with self.lock:
            state = tr.state()
        self.sync_journal()
        if self.journal is not None and self.journal.error:
            return None  # (a full checkpoint is due instead)
        t0 = time.perf_counter()
        try:
            path = save_model(self.ckpt_dir, tr.algo, state)
        except Exception as exc:
            if not is_disk_fault(exc):
                raise
            self.saves.failed(exc, self.not_durable(), "model checkpoint")
            return None
        self.saves.succeeded()
        self.model_checkpoints += 1
        self.last_model_iterations = int(state["iterations"])
        log.debug("model checkpoint %d: version %d, %d iterations (%.2f s)", self.model_checkpoints, state["version"],
                  state["iterations"], time.perf_counter() - t0)
        return path

    def checkpoint(self) -> Path | None:
        """Save a full checkpoint of everything accepted so far (model and replay buffer), then tell every actor
        (``durable`` in the acks) and delete the journal's segments before it. With a working journal, ingest
        pauses only while the journal is cut and the replay buffer copied (what comes meanwhile goes to the
        journal's next segment); without one (or after a journal write failed) it waits for the whole save. A disk
        fault (full, read-only, unwritable) leaves the previous checkpoint and marks nothing new durable: it is
        logged, shown in the status, retried with backoff (:class:`~khgrl.learner.disk_faults.SaveFaults`), and None
        returned."""
        j = self.journal
        with self.lock:  # ingest waits (the inbox holds what arrives): the buffer is taken as the acks will say
            index = None
            if j is not None:  # what waits is written; later batches go to a new segment, replayed after this one
                index, marks, exc = j.cut()
                self._durable(marks)
                if exc is not None:
                    self.saves.failed(exc, self.not_durable(), "journal write")
            snap = self._snapshot(index)
            if j is None or j.error:  # the snapshot must hold what the journal missed: ingest waits for the save
                return self._save_snapshot(snap)
            snap["buffer"] = copy_buffer(self.trainer.buffer)
        return self._save_snapshot(snap)

    def _snapshot(self, index: int | None) -> dict[str, Any]:
        """What a full checkpoint holds, taken with :attr:`lock` held (the replay buffer: the live one)."""
        tr = self.trainer
        state = {**tr.state(), **self.streams.state(), **({} if index is None else {"journal": {"next": index}})}
        return {"state": state, "buffer": None, "index": index, "total": tr.total, "iterations": tr.iterations,
                "held": {id(st): (st, st.next_seq - 1) for st in (self.streams[a] for a in self.streams)},
                "t0": time.perf_counter()}

    def _save_snapshot(self, snap: dict[str, Any]) -> Path | None:
        tr = self.trainer
        try:
            path = save_checkpoint(self.ckpt_dir, tr.algo, snap["state"], buffer=snap["buffer"])
        except Exception as exc:
            if not is_disk_fault(exc):
                raise
            self.saves.failed(exc, self.not_durable())
            return None
        with self.lock:
            self.saves.succeeded()
            if self.journal is not None:
                self.journal.snapshot_saved(snap["index"])
            self.last_ckpt_total = snap["total"]
            self.last_model_iterations = max(self.last_model_iterations, snap["iterations"])
            self.checkpoints += 1
            self._durable(snap["held"])  # (acks every actor)
        log.info("checkpoint %d: %d transitions, version %d, %d iterations (%.2f s)", self.checkpoints, snap["total"],
                 snap["state"]["version"], snap["iterations"], time.perf_counter() - snap["t0"])
        return path

    def sync_loop(self, flag: Any) -> None:
        """The journal thread: write and fsync what the ingest thread journaled, as soon as something waits
        (whatever arrives during one fsync goes into the next), until the stop flag is set.

        :param flag: the process's stop flag (set here if this thread fails)
        """
        try:
            while not flag:
                if self.journal.wake.wait(IDLE_WAIT_S):
                    self.journal.wake.clear()
                    self.sync_journal()
            self.sync_journal()
        except Exception:  # noqa: BLE001 - a bug here must stop the learner, not leave acks claiming nothing
            log.exception("journal thread failed")
            flag.set("journal thread failed")

    def settle_loss(self) -> Path | None:
        """A learner resumed past journal damage the operator accepted (``streams.journal_loss``): the journal's mark
        says confirmed only what the streams hold now, and a full checkpoint at once replaces the damaged segments
        (so that the next resume neither finds that damage again nor counts that loss twice). Returns the checkpoint
        (None: it failed, retried on its schedule)."""
        if self.journal is not None:
            self.journal.restart_mark({a: (st.stream, st.next_seq - 1) for a, st in self.streams.streams.items()})
        return self.checkpoint()

    def lost_batches(self) -> int:
        """Confirmed batches this learner lacks: holes of an accepted journal loss, its tails that no actor re-sent,
        and the batches skipped since the start (no actor held them any more)."""
        loss = self.streams.journal_loss
        lost = loss.hole_batches + loss.unfilled_tails(self.streams) if loss is not None else 0
        return lost + self.streams.skipped

    def summary(self) -> dict[str, Any]:
        """Counters for the log line at the end."""
        loss = self.streams.journal_loss
        return {"checkpoints": self.checkpoints, "model_checkpoints": self.model_checkpoints,
                "journal": self.journal.info() if self.journal is not None else None,
                "lost_batches": self.lost_batches(), "journal_loss": loss.summary() if loss is not None else None}
