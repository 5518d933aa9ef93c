"""The learner's main loop, without Zenoh: messages in, acks / weights / status out through a publisher.

:meth:`LearnerLoop.run` keeps ingest apart from training. Its *ingest thread* takes messages as they arrive
(served per actor, :class:`~khgrl.common.delivery.ingest.FairInbox`), decodes and checks them, stores accepted batches
in the
replay buffer and acks their actors; it never waits for a gradient step. The calling thread trains -- one due
iteration at a time (``simulation`` mode: the schedule of SB3's ``learn()``; ``robot`` mode: whenever it is
free, on everything stored) -- publishes the new weights and acks every actor, checkpoints when due or asked
to (ingest pauses meanwhile), and publishes a status about once a second. Memory stays bounded: the inbox is
bounded in messages and bytes, each actor has at most its window of batches out, and the replay buffer has
its capacity.

Unit tests drive the same steps in one thread: :meth:`LearnerLoop.offer` / :meth:`LearnerLoop.control` with
decoded messages (or :meth:`LearnerLoop.receive` with payload bytes), then :meth:`LearnerLoop.step`, with a
publisher that collects the typed messages.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Protocol

from khgrl.common.delivery.ingest import FairInbox, StreamTable
from khgrl.common.process import StopFlag
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import LearnerInfo
from khgrl.common.wire.protocol import (
    ANY_DIMS,
    Ack,
    Control,
    Dims,
    Keys,
    ProtocolError,
    RejectCounter,
    Status,
    Transitions,
    Weights,
    attribute_control,
    decode,
)
from khgrl.learner.checkpoint import SaveFaults, fault_reason, is_disk_fault, save_checkpoint
from khgrl.learner.resume import open_learner, rss_mb
from khgrl.learner.trainer import Trainer

__all__ = ["Publisher", "LearnerLoop", "open_learner", "MAX_DRAIN"]

log = logging.getLogger("khgrl.learner")

MAX_DRAIN = 512  # messages taken per turn before the loop trains / acks / checkpoints
IDLE_WAIT_S = 0.05  # how long a turn waits for the first message when there is nothing to train
STATUS_EVERY_S = 1.0


class Publisher(Protocol):
    """Where the loop's messages go (Zenoh in the process, a list in tests)."""

    queries: int  # weights queries answered so far

    def weights(self, msg: Weights) -> None: ...

    def ack(self, msg: Ack) -> None: ...

    def status(self, msg: Status) -> None: ...


class _Inbox(Protocol):
    def get(self, timeout: float = 0.0) -> tuple | None: ...

    def qsize(self) -> int: ...


class LearnerLoop:
    """Stream ordering, training, acks, weights, checkpoints and status of one learner incarnation."""

    def __init__(self, trainer: Trainer, streams: StreamTable, publisher: Publisher, *, learner_id: str,
                 learner_dir: str | Path, checkpoint_every: int, flag: StopFlag,
                 clock: Callable[[], float] = time.monotonic, checkpoint_dir: str | Path | None = None,
                 mode: str = "simulation") -> None:
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
        """
        self.trainer, self.streams, self.pub = trainer, streams, publisher
        self.id = learner_id
        self.dir = Path(learner_dir)
        self.ckpt_dir = Path(checkpoint_dir or learner_dir)
        self.saves = SaveFaults(clock)  # failed checkpoint saves (disk faults) and their retry backoff
        self.checkpoint_every = int(checkpoint_every)
        self.flag = flag
        self.clock = clock
        self.rejects = RejectCounter(f"learner/{learner_id}")
        self.results: Counter = Counter()  # offers by result
        self.paused = False
        self.checkpoint_requested = False
        self.checkpoints = 0
        self.last_ckpt_total = trainer.total
        self.train_time = 0.0
        self.scalar_faults = 0  # training scalars the SB3 logger could not write
        self.touched: set[str] = set()
        self.inbox: _Inbox | None = None
        self.task: TaskDescriptor | None = None  # the run's task: batches of other sizes or tasks are refused
        self.dims = ANY_DIMS
        self.mode = mode
        trainer.schedule = mode == "simulation"
        self.lock = threading.RLock()  # streams, counters and acks between the ingest and training threads
        self.wake = threading.Event()  # set by ingest when there may be something to train
        now = clock()
        self._status_t, self._status_steps = now, trainer.gradient_steps

    # ------------------------------------------------------------------------------------ input
    def receive(self, kind: str, key: str, payload: bytes) -> None:
        """One message as it arrived (``kind`` as filed by the inbox); a bad one is counted and logged.

        :param kind: 'transitions', 'control' (``control/learner``, ``control/all``) or 'request' (a ``control``
            message on ``actor/<id>/request``: only ``checkpoint`` from that actor is taken there)
        :param key: the key expression it arrived on
        :param payload: its bytes
        """
        try:
            if kind == "request":
                self.request(decode(Control, payload), key)
            elif kind == "transitions":
                msg = decode(Transitions, payload, self.dims)
                if msg.actor != Keys.chunk(key, 3):
                    raise ProtocolError(f"actor {msg.actor!r} published on {key}")
                if self.task is not None and msg.task is not None and msg.task != self.task.digest:
                    raise ProtocolError(f"actor {msg.actor} runs a task with digest {msg.task}, this learner was built "
                                        f"for {self.task.name!r} (digest {self.task.digest}): start them with one task")
                self.offer(msg)
            else:
                cmd = decode(Control, payload)
                attribute_control(cmd, key, log)
                self.control(cmd)
        except ProtocolError as exc:
            self.rejects.reject("control" if kind == "request" else kind, key, exc)

    def request(self, msg: Control, key: str) -> None:
        """An actor's request on its ``actor/<id>/request``: a ``checkpoint`` from that actor, nothing else (raises
        :class:`ProtocolError`).

        :param msg: the decoded message
        :param key: the key it came on
        """
        if msg.command != "checkpoint":
            raise ProtocolError(f"command {msg.command!r} on {key}: an actor may only request a checkpoint")
        if msg.envelope is not None and msg.envelope.sender != Keys.chunk(key, 3):
            raise ProtocolError(f"sender {msg.envelope.sender!r} published on {key}")
        self.control(msg)

    def set_task(self, task) -> None:
        """The run's task descriptor: transitions are checked against its sizes and digest, acks carry its digest.

        :param task: a :class:`~khgrl.common.wire.descriptor.TaskDescriptor`
        """
        self.task = task
        self.dims = Dims(obs=task.obs_dim, out=task.out_dim)

    def _ack(self, actor: str) -> Ack:
        ack = self.trainer.ack(self.streams[actor])
        return ack if self.task is None else ack.replace(task=self.task.digest)

    def offer(self, msg: Transitions) -> str:
        """A decoded batch: ordered into its actor's stream and, when accepted, stored (with any batches it
        unblocked). Returns 'accepted', 'duplicate', 'held' or 'superseded'; the actor is acked at the next
        :meth:`step` (a superseded stream at once, with ``superseded`` set: its process stops).

        :param msg: the batch
        """
        with self.lock:
            res = self.streams.offer(msg)
            self.results[res.result] += 1
            if res.result == "superseded":  # a later stream of this actor id was taken: this one is refused
                self.pub.ack(self._ack(msg.actor).replace(received=-1, durable=-1, trained=0, stream=msg.stream,
                                                          superseded=True))
                return res.result
            for batch in res.ready:
                self.trainer.add(batch, res.stream, self.streams.positions)
            self.touched.add(msg.actor)
        if res.ready:
            self.wake.set()
        return res.result

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

    def drain(self, inbox: _Inbox) -> int:
        """Take up to :data:`MAX_DRAIN` messages (waiting briefly for the first when there is nothing to train).

        :param inbox: a :class:`khgrl.common.delivery.transport.Inbox` (items ``(kind, key, payload, arrival)``)
        """
        n = 0
        while n < MAX_DRAIN:
            idle = n == 0 and (not self.trainer.due or self.paused)
            item = inbox.get(IDLE_WAIT_S if idle else 0.0)
            if item is None:
                break
            kind, key, payload = item[:3]
            self.receive(kind, key, payload)
            n += 1
        return n

    # ------------------------------------------------------------------------------------ output
    def start(self) -> None:
        """Publish the current weights (version 0, or the resumed version) and ack every known stream (after a
        resume, actors re-send everything after the checkpoint)."""
        self.pub.weights(self.trainer.weights())
        self.ack_all()

    def ack_all(self) -> None:
        """Ack every known actor stream."""
        with self.lock:
            for actor in list(self.streams):
                self.pub.ack(self._ack(actor))

    def ack_touched(self) -> None:
        """Ack the actors whose batches arrived since the last call."""
        with self.lock:
            for actor in sorted(self.touched):
                self.pub.ack(self._ack(actor))
            self.touched.clear()

    def step(self) -> None:
        """After messages were taken in: ack, then :meth:`work`."""
        self.ack_touched()
        self.work()

    def work(self) -> bool:
        """Train one iteration (unless paused; simulation mode: if one is due), checkpoint when due (after a failed
        save: once its retry is due), publish status when its time has come. Returns whether it trained."""
        trained = not self.paused and (self.mode == "robot" or bool(self.trainer.due)) and self.train()
        every = self.checkpoint_every
        due = self.checkpoint_requested or (every > 0 and self.trainer.total - self.last_ckpt_total >= every)
        if due and self.saves.ready():
            self.checkpoint_requested = False
            self.checkpoint()
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
            self.trainer.record_iteration(dt, self.queue_depth())
        except OSError as exc:  # SB3's scalar files on a full or read-only disk: those scalars are lost, nothing else
            self.scalar_faults += 1
            if self.scalar_faults in (1, 10) or self.scalar_faults % 1000 == 0:
                log.warning("training scalars not written (%s; %d times); training goes on", fault_reason(exc),
                            self.scalar_faults)
        return True

    def checkpoint(self) -> Path | None:
        """Save a checkpoint of everything accepted so far, then tell every actor (``durable`` in the acks). A disk
        fault (full, read-only, unwritable) leaves the previous checkpoint and marks nothing durable: it is logged,
        shown in the status, retried with backoff (:class:`~khgrl.learner.checkpoint.SaveFaults`), and None returned."""
        with self.lock:  # ingest waits (the inbox holds what arrives): the buffer is saved as the acks will say
            return self._checkpoint()

    def _checkpoint(self) -> Path | None:
        t0 = time.perf_counter()
        tr = self.trainer
        try:
            path = save_checkpoint(self.ckpt_dir, tr.algo, {**tr.state(), **self.streams.state()})
        except Exception as exc:
            if not is_disk_fault(exc):
                raise
            self.saves.failed(exc, tr.total - self.last_ckpt_total)
            return None
        self.saves.succeeded()
        self.streams.mark_durable()
        self.last_ckpt_total = tr.total
        self.checkpoints += 1
        log.info("checkpoint %d: %d transitions, version %d, %d iterations (%.2f s)", self.checkpoints, tr.total,
                 tr.version, tr.iterations, time.perf_counter() - t0)
        self.ack_all()
        return path

    def queue_depth(self) -> int:
        """Messages waiting in the inbox (0 when driven without one)."""
        return self.inbox.qsize() if self.inbox is not None else 0

    def info(self) -> LearnerInfo:
        """This learner's status (the rate: gradient steps per second since the previous call)."""
        with self.lock:
            return self._info()

    def _info(self) -> LearnerInfo:
        tr, now = self.trainer, self.clock()
        rate = (tr.gradient_steps - self._status_steps) / max(now - self._status_t, 1e-9)
        self._status_t, self._status_steps = now, tr.gradient_steps
        streams = [self.streams[a] for a in self.streams]
        return LearnerInfo(id=self.id, epoch=tr.epoch, ingested=tr.total, iterations=tr.iterations,
                           gradient_steps=tr.gradient_steps, grad_steps_per_s=round(rate, 2), version=tr.version,
                           pending_iterations=len(tr.due), queue_depth=self.queue_depth(),
                           rejects=self.rejects.by_kind(), paused=self.paused, checkpoints=self.checkpoints,
                           next_seq={st.actor: st.next_seq for st in streams},
                           durable={st.actor: st.durable for st in streams},
                           duplicates={st.actor: st.duplicates for st in streams},
                           weights_queries=int(self.pub.queries), checkpoint_error=self.saves.error,
                           checkpoint_failures=self.saves.failures, mode=self.mode, utd=round(tr.utd, 4),
                           rss_mb=rss_mb(), not_admitted_dropped=int(getattr(self.inbox, "dropped", 0)))

    def publish_status(self) -> None:
        """Publish :meth:`info` as this learner's status."""
        self.pub.status(Status(role="learner", info=self.info()))

    # ------------------------------------------------------------------------------------ the loop
    def run(self, inbox: _Inbox) -> None:
        """Turn until the stop flag is set (SIGINT/SIGTERM or a ``stop`` command). The caller checkpoints last.

        :param inbox: where the Zenoh callbacks file transitions and control messages (served per actor, see
            :class:`~khgrl.common.delivery.ingest.FairInbox`)
        """
        inbox = self.inbox = FairInbox(inbox, self.streams.__contains__)
        ingest = threading.Thread(target=self._ingest, args=(inbox,), name="ingest", daemon=True)
        ingest.start()
        try:
            while not self.flag:
                if not self.work():
                    self.wake.wait(IDLE_WAIT_S)
                    self.wake.clear()
        finally:
            self.flag.set("stop")
            ingest.join(10.0)

    def _ingest(self, inbox: _Inbox) -> None:
        """The ingest thread: take in, store and ack what arrives until the stop flag is set."""
        try:
            while not self.flag:
                item = inbox.get(IDLE_WAIT_S)
                n = 0
                while item is not None:
                    self.receive(*item[:3])
                    n += 1
                    item = inbox.get(0.0) if n < MAX_DRAIN else None
                self.ack_touched()
        except Exception:  # noqa: BLE001 - a bug here must stop the learner, not leave it training on nothing
            log.exception("ingest thread failed")
            self.flag.set("ingest thread failed")

    def summary(self) -> dict[str, Any]:
        """Totals for the log line at the end."""
        tr = self.trainer
        return {"transitions": tr.total, "iterations": tr.iterations, "gradient_steps": tr.gradient_steps,
                "train_s": round(self.train_time, 1), "version": tr.version, "rejected": self.rejects.by_kind(),
                "offers": dict(self.results), "not_admitted_dropped": getattr(self.inbox, "dropped", 0)}
