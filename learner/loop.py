"""The learner's main loop: training, weights, checkpoints and status; what arrives goes through the delivery layer.

:meth:`LearnerLoop.run` keeps ingest apart from training. The ingest thread
(:class:`~khgrl.common.delivery.learner_side.LearnerIngest`) decodes and checks what arrives, orders it per actor,
stores accepted batches in the replay buffer (``trainer.add``) and acks their actors; it never waits for a gradient
step. The calling thread trains -- one due iteration at a time (``simulation`` mode: the schedule of SB3's
``learn()``; ``robot`` mode: whenever it is free, on everything stored) -- publishes the new weights and acks every
actor, checkpoints when due or asked to (ingest pauses meanwhile), and publishes a status about once a second.

Durability (with a :class:`~khgrl.learner.journal.Journal`, the default): every batch stored is also appended to
the journal; the *journal thread* writes and fsyncs what waits as one group and acks its actors with the new
``durable`` (the highest seq on disk). The model is saved on its own schedule (``model_checkpoint_every``
training iterations: ``model/``, small); the full checkpoint -- model and whole replay buffer, ``checkpoint/`` --
is rare: when the journal since the last one holds a replay buffer's worth of transitions (or every
``checkpoint_every``), when the journal failed (disk fault: the snapshot holds what the journal missed), and at
the end; the journal's older segments are then deleted. An actor's ``checkpoint`` request syncs the journal and
saves the model. Without a journal, full checkpoints alone make batches durable (every ``checkpoint_every``,
on request, at the end).

Unit tests drive the same steps in one thread: :meth:`LearnerLoop.offer` / :meth:`LearnerLoop.control` with decoded
messages (or :meth:`LearnerLoop.receive` with payload bytes), then :meth:`LearnerLoop.step`, with a publisher that
collects the typed messages.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any, Callable

from khgrl.common.delivery.ingest import StreamTable
from khgrl.common.delivery.learner_link import Publisher
from khgrl.common.delivery.learner_side import IDLE_WAIT_S, LearnerIngest
from khgrl.common.process import StopFlag
from khgrl.common.wire.messages import LearnerInfo
from khgrl.common.wire.protocol import Control, Status
from khgrl.learner.checkpoint import SaveFaults, copy_buffer, fault_reason, is_disk_fault, save_checkpoint, save_model
from khgrl.learner.journal import Journal
from khgrl.learner.resume import open_learner, rss_mb
from khgrl.learner.trainer import Trainer

__all__ = ["Publisher", "LearnerLoop", "open_learner"]

log = logging.getLogger("khgrl.learner")

STATUS_EVERY_S = 1.0


class LearnerLoop:
    """Training, weights, checkpoints and status of one learner incarnation; receiving, ordering and acks in
    :attr:`ingest` (:class:`~khgrl.common.delivery.learner_side.LearnerIngest`)."""

    def __init__(self, trainer: Trainer, streams: StreamTable, publisher: Publisher, *, learner_id: str,
                 learner_dir: str | Path, checkpoint_every: int, flag: StopFlag,
                 clock: Callable[[], float] = time.monotonic, checkpoint_dir: str | Path | None = None,
                 mode: str = "simulation", journal: Journal | None = None, model_checkpoint_every: int = 0,
                 snapshot_rows: int | None = None) -> None:
        """:param trainer: the model and its schedule
        :param streams: the actor streams (empty, or from a checkpoint)
        :param publisher: where acks, weights and status go
        :param learner_id: this learner's id (status)
        :param learner_dir: ``RUN_DIR/learner`` (checkpoints)
        :param checkpoint_every: checkpoint every N ingested transitions (0: only when asked and at the end)
        :param flag: the process's stop flag (a ``stop`` command sets it)
        :param clock: monotonic seconds (status period, checkpoint retries)
        :param checkpoint_dir: where checkpoints go (None: ``learner_dir``)
        :param mode: ``simulation`` (iterations come due with the data) or ``robot`` (train whenever free)
        :param journal: the journal of stored batches (None: only full checkpoints make batches durable)
        :param model_checkpoint_every: with a journal, save the model every N training iterations (0: only in
            full checkpoints)
        :param snapshot_rows: with a journal, a full checkpoint once it holds this many transitions since the last
            one (None: the replay buffer's size)
        """
        self.trainer, self.streams, self.pub = trainer, streams, publisher
        self.id = learner_id
        self.dir = Path(learner_dir)
        self.ckpt_dir = Path(checkpoint_dir or learner_dir)
        self.saves = SaveFaults(clock)  # failed checkpoint saves (disk faults) and their retry backoff
        self.checkpoint_every = int(checkpoint_every)
        self.flag = flag
        self.clock = clock
        self.paused = False
        self.checkpoint_requested = False
        self.checkpoints = 0
        self.last_ckpt_total = trainer.total
        self.journal = journal
        self.model_every = int(model_checkpoint_every) if journal is not None else 0
        self.snapshot_rows = int(snapshot_rows or trainer.buffer.buffer_size)
        self.model_checkpoints = 0
        self.last_model_iterations = trainer.iterations
        self.train_time = 0.0
        self.scalar_faults = 0  # training scalars the SB3 logger could not write
        self.mode = mode
        trainer.schedule = mode == "simulation"
        store = trainer.add if journal is None else self._store
        self.ingest = ing = LearnerIngest(streams, publisher, store=store, ack_of=trainer.ack,
                                          on_control=self.control, learner_id=learner_id, flag=flag)
        self.receive, self.offer, self.set_task, self.ack_all = ing.receive, ing.offer, ing.set_task, ing.ack_all
        self.rejects, self.lock, self.wake = ing.rejects, ing.lock, ing.wake
        now = clock()
        self._status_t, self._status_steps = now, trainer.gradient_steps

    @property
    def inbox(self) -> Any:
        """The fair inbox the ingest thread takes from (None when driven without one)."""
        return self.ingest.inbox

    @inbox.setter
    def inbox(self, inbox: Any) -> None:
        self.ingest.inbox = inbox

    def control(self, msg: Control) -> None:
        """A decoded control command: stop, checkpoint, pause or resume training.

        :param msg: the command
        """
        self.wake.set()
        if msg.command == "stop":
            self.flag.set("stop command")
        elif msg.command == "checkpoint":
            self.checkpoint_requested = True
        elif msg.command in ("pause", "resume"):
            self.paused = msg.command == "pause"

    # ------------------------------------------------------------------------------------ output
    def start(self) -> None:
        """Publish the current weights (version 0, or the resumed version) and ack every known stream (after a
        resume, actors re-send everything after the checkpoint)."""
        self.pub.weights(self.trainer.weights())
        self.ack_all()

    def step(self) -> None:
        """After messages were taken in: ack, sync the journal (what the journal thread does), then :meth:`work`."""
        self.ingest.ack_touched()
        self.sync_journal()
        self.work()

    def work(self) -> bool:
        """Train one iteration (unless paused; simulation mode: if one is due), checkpoint when due (after a failed
        save: once its retry is due), publish status when its time has come. Returns whether it trained."""
        trained = not self.paused and (self.mode == "robot" or bool(self.trainer.due)) and self.train()
        self.durability()
        if self.clock() - self._status_t >= STATUS_EVERY_S:
            self.publish_status()
        return trained

    def durability(self) -> None:
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
            self.ack_all()
        elif self.model_every and tr.iterations - self.last_model_iterations >= self.model_every and \
                self.saves.ready():
            self.save_model()

    def train(self) -> bool:
        """One training iteration (simulation mode: the next due one; robot mode: on everything stored), then the
        new weights and acks for every actor."""
        t0 = time.perf_counter()
        if self.mode == "robot":
            with self.lock:
                positions = self.streams.positions()
            if not self.trainer.train_now(positions):
                return False
        elif not self.trainer.train_one():
            return False
        dt = time.perf_counter() - t0
        self.train_time += dt
        self.pub.weights(self.trainer.weights())
        self.ack_all()
        try:
            self.trainer.record_iteration(dt, self.ingest.queue_depth())
        except OSError as exc:  # SB3's scalar files on a full or read-only disk: those scalars are lost, nothing else
            self.scalar_faults += 1
            if self.scalar_faults in (1, 10) or self.scalar_faults % 1000 == 0:
                log.warning("training scalars not written (%s; %d times); training goes on", fault_reason(exc),
                            self.scalar_faults)
        return True

    # ------------------------------------------------------------------------------------ durability
    def _store(self, batch: Any, stream: Any, positions: Callable[[], dict[str, int]]) -> None:
        """Store an accepted batch (ingest thread, :attr:`lock` held) and journal it."""
        self.trainer.add(batch, stream, positions)
        self.journal.append(batch, stream)

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
                self.pub.ack(self.ingest.ack(stream.actor))

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
        logged, shown in the status, retried with backoff (:class:`~khgrl.learner.checkpoint.SaveFaults`), and None
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

    def info(self) -> LearnerInfo:
        """This learner's status (the rate: gradient steps per second since the previous call)."""
        with self.lock:
            tr, now = self.trainer, self.clock()
            rate = (tr.gradient_steps - self._status_steps) / max(now - self._status_t, 1e-9)
            self._status_t, self._status_steps = now, tr.gradient_steps
            return LearnerInfo(id=self.id, epoch=tr.epoch, ingested=tr.total, iterations=tr.iterations,
                               gradient_steps=tr.gradient_steps, grad_steps_per_s=round(rate, 2), version=tr.version,
                               pending_iterations=len(tr.due), paused=self.paused, checkpoints=self.checkpoints,
                               checkpoint_error=self.saves.error, checkpoint_failures=self.saves.failures,
                               mode=self.mode, utd=round(tr.utd, 4), rss_mb=rss_mb(), **self.ingest.info())

    def publish_status(self) -> None:
        """Publish :meth:`info` as this learner's status."""
        self.pub.status(Status(role="learner", info=self.info()))

    # ------------------------------------------------------------------------------------ the loop
    def run(self, inbox: Any) -> None:
        """Turn until the stop flag is set (SIGINT/SIGTERM or a ``stop`` command). The caller checkpoints last.

        :param inbox: where the learner's link files transitions and control messages (the ingest thread's)
        """
        ingest = self.ingest.start(inbox)
        syncer = None
        if self.journal is not None:
            syncer = threading.Thread(target=self._sync_loop, name="journal", daemon=True)
            syncer.start()
        try:
            while not self.flag:
                if not self.work():
                    self.wake.wait(IDLE_WAIT_S)
                    self.wake.clear()
        finally:
            self.flag.set("stop")
            ingest.join(10.0)
            if syncer is not None:
                syncer.join(10.0)

    def _sync_loop(self) -> None:
        """The journal thread: write and fsync what the ingest thread journaled, as soon as something waits
        (whatever arrives during one fsync goes into the next), until the stop flag is set."""
        try:
            while not self.flag:
                if self.journal.wake.wait(IDLE_WAIT_S):
                    self.journal.wake.clear()
                    self.sync_journal()
            self.sync_journal()
        except Exception:  # noqa: BLE001 - a bug here must stop the learner, not leave acks claiming nothing
            log.exception("journal thread failed")
            self.flag.set("journal thread failed")

    def summary(self) -> dict[str, Any]:
        """Totals for the log line at the end."""
        tr = self.trainer
        return {"transitions": tr.total, "iterations": tr.iterations, "gradient_steps": tr.gradient_steps,
                "train_s": round(self.train_time, 1), "version": tr.version, "rejected": self.rejects.by_kind(),
                "offers": dict(self.ingest.results), "not_admitted_dropped": self.ingest.dropped,
                "checkpoints": self.checkpoints, "model_checkpoints": self.model_checkpoints,
                "journal": self.journal.info() if self.journal is not None else None}
