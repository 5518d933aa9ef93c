"""The learner's main loop: training, weights, checkpoints and status; what arrives goes through the delivery layer.

:meth:`LearnerLoop.run` keeps ingest apart from training. The ingest thread
(:class:`~khgrl.common.delivery.learner_side.LearnerIngest`) decodes and checks what arrives, orders it per actor,
stores accepted batches in the replay buffer (``trainer.add``) and acks their actors; it never waits for a gradient
step. The calling thread trains -- one due iteration at a time (``simulation`` mode: the schedule of SB3's
``learn()``; ``robot`` mode: whenever it is free, on everything stored) -- publishes the new weights and acks every
actor, checkpoints when due or asked to, and publishes a status about once a second.

Durability -- the journal (synced by its own *journal thread*), the model checkpoint and the rare full checkpoint --
is :attr:`LearnerLoop.durable` (:class:`~khgrl.learner.durability.Durability`).
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
from khgrl.learner.disk_faults import fault_reason
from khgrl.learner.durability import Durability
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
                 snapshot_rows: int | None = None, lead_cap: int | None = None, key: Any = None) -> None:
        """:param trainer: the model and its schedule
        :param streams: the actor streams (empty, or from a checkpoint)
        :param publisher: where acks, weights and status go
        :param learner_id: this learner's id (status)
        :param learner_dir: ``RUN_DIR/learner`` (checkpoints)
        :param checkpoint_every: full checkpoint every N ingested transitions (0: the journal's schedule; without a
            journal, only when asked and at the end)
        :param flag: the process's stop flag (a ``stop`` command sets it)
        :param clock: monotonic seconds (status period, checkpoint retries)
        :param checkpoint_dir: where checkpoints go (None: ``learner_dir``)
        :param mode: ``simulation`` (iterations come due with the data) or ``robot`` (train whenever free)
        :param journal: the journal of stored batches (None: only full checkpoints make batches durable)
        :param model_checkpoint_every: with a journal, save the model every N training iterations (0: only in
            full checkpoints)
        :param snapshot_rows: with a journal, a full checkpoint once it holds this many transitions since the last
            one (None: the replay buffer's size)
        :param lead_cap: simulation mode: transitions of an actor stored ahead of what trained weights cover, at
            most (:attr:`~khgrl.common.delivery.learner_side.LearnerIngest.lead_cap`; None: no cap)
        :param key: the run's key: batches without its ``mac`` are refused (None: none checked)
        """
        self.trainer, self.streams, self.pub = trainer, streams, publisher
        self.id = learner_id
        self.dir = Path(learner_dir)
        self.ckpt_dir = Path(checkpoint_dir or learner_dir)
        self.durable = dur = Durability(trainer, streams, self.ckpt_dir, checkpoint_every=checkpoint_every, clock=clock,
                                        journal=journal, model_every=model_checkpoint_every,
                                        snapshot_rows=snapshot_rows)
        self.flag = flag
        self.clock = clock
        self.paused = False
        self.train_time = 0.0
        self.scalar_faults = 0  # training scalars the SB3 logger could not write
        self.mode = mode
        trainer.schedule = mode == "simulation"
        self.ingest = dur.ingest = ing = LearnerIngest(streams, publisher, store=dur.store, ack_of=trainer.ack,
                                                       on_control=self.control, learner_id=learner_id, flag=flag,
                                                       key=key)
        ing.lead_cap = lead_cap if mode == "simulation" else None
        trainer.buffer.stream_codes = streams.codes  # (the replay buffer's shares are per actor id)
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
        self.durable.sync_journal()
        self.work()

    def work(self) -> bool:
        """Train one iteration (unless paused; simulation mode: if one is due), checkpoint when due (after a failed
        save: once its retry is due), publish status when its time has come. Returns whether it trained."""
        trained = not self.paused and (self.mode == "robot" or bool(self.trainer.due)) and self.train()
        self.durable.work()
        if self.clock() - self._status_t >= STATUS_EVERY_S:
            self.publish_status()
        return trained

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
    def checkpoint(self) -> Path | None:
        """A full checkpoint now (:meth:`~khgrl.learner.durability.Durability.checkpoint`); None if it failed."""
        return self.durable.checkpoint()

    @property
    def checkpoint_requested(self) -> bool:
        """A ``checkpoint`` command waits to be served."""
        return self.durable.checkpoint_requested

    @checkpoint_requested.setter
    def checkpoint_requested(self, value: bool) -> None:
        self.durable.checkpoint_requested = value

    def info(self) -> LearnerInfo:
        """This learner's status (the rate: gradient steps per second since the previous call)."""
        sampling = self.trainer.buffer.sampling_info()  # (its own lock, not taken inside the ingest lock)
        with self.lock:
            tr, now, saves = self.trainer, self.clock(), self.durable.saves
            rate = (tr.gradient_steps - self._status_steps) / max(now - self._status_t, 1e-9)
            self._status_t, self._status_steps = now, tr.gradient_steps
            return LearnerInfo(id=self.id, epoch=tr.epoch, ingested=tr.total, iterations=tr.iterations,
                               gradient_steps=tr.gradient_steps, grad_steps_per_s=round(rate, 2), version=tr.version,
                               pending_iterations=len(tr.due), paused=self.paused, checkpoints=self.durable.checkpoints,
                               checkpoint_error=saves.error, checkpoint_failures=saves.failures,
                               mode=self.mode, utd=round(tr.utd, 4), rss_mb=rss_mb(), rollbacks=tr.rollbacks,
                               **sampling, **self.ingest.info())

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
        if self.durable.journal is not None:
            syncer = threading.Thread(target=self.durable.sync_loop, args=(self.flag,), name="journal", daemon=True)
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

    def summary(self) -> dict[str, Any]:
        """Totals for the log line at the end."""
        tr = self.trainer
        return {"transitions": tr.total, "iterations": tr.iterations, "gradient_steps": tr.gradient_steps,
                "train_s": round(self.train_time, 1), "version": tr.version, "rollbacks": tr.rollbacks,
                "q_rollbacks": tr.q_rollbacks, **(tr.watch.summary() if tr.watch is not None else {}),
                "rejected": self.rejects.by_kind(), "offers": dict(self.ingest.results),
                "not_admitted_dropped": self.ingest.dropped, **self.durable.summary()}
