"""The learner's main loop, without Zenoh: messages in, acks / weights / status out through a publisher.

Each turn of :meth:`LearnerLoop.run` takes what has arrived (a bounded number of messages, so training and
acks interleave with the stream), acks the actors whose batches came in, runs at most one due training
iteration and publishes the new weights (and acks for every actor), checkpoints when due or asked to, and
publishes a status about once a second. Unit tests drive the same steps directly: :meth:`LearnerLoop.offer`
/ :meth:`LearnerLoop.control` with decoded messages (or :meth:`LearnerLoop.receive` with payload bytes), then
:meth:`LearnerLoop.step`, with a publisher that collects the typed messages.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Protocol

from common.config import TQCSettings
from common.descriptor import TaskDescriptor
from common.messages import LearnerInfo
from common.process import StopFlag
from common.protocol import (
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
    decode,
)
from common.spaces import SpacesEnv
from learner.checkpoint import CheckpointError, find_checkpoint, load_checkpoint, save_checkpoint
from learner.ingest import StreamTable
from learner.trainer import Trainer, build_model

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


def open_learner(tqc: TQCSettings, seed: int, learner_dir: str | Path, *, resume: bool,
                 logger_formats: tuple[str, ...] = ("csv", "tensorboard"), task=None) -> tuple[Trainer, StreamTable]:
    """A fresh model and empty stream table, or (``resume``) both as the newest checkpoint left them.

    :param tqc: the run's TQC settings (schedule: ``learning_starts``, ``train_freq``)
    :param seed: the model's seed (a fresh model only)
    :param learner_dir: ``RUN_DIR/learner`` (checkpoint, SB3 logs under ``tb/``)
    :param resume: continue from the checkpoint (:class:`CheckpointError` if there is none)
    :param logger_formats: SB3 logger output formats
    :param task: the run's :class:`~common.descriptor.TaskDescriptor` (None: the passage world's spaces)
    """
    learner_dir = Path(learner_dir)
    learner_dir.mkdir(parents=True, exist_ok=True)
    kw = dict(learning_starts=tqc.learning_starts, train_freq=tqc.train_freq, log_dir=learner_dir / "tb",
              logger_formats=logger_formats)
    if not resume:
        return Trainer(build_model(tqc, seed, task), **kw), StreamTable()
    ckpt = find_checkpoint(learner_dir)
    if ckpt is None:
        raise CheckpointError(f"--resume: no checkpoint under {learner_dir}")
    model, state = load_checkpoint(ckpt, SpacesEnv(task))
    trainer, streams = Trainer(model, **kw), StreamTable.from_state(state)
    trainer.restore(state)
    log.info("resumed from %s: %d transitions (buffer pos %d), version %d, %d iterations, actors %s", ckpt,
             trainer.total, trainer.buffer.pos, trainer.version, trainer.iterations,
             {a: streams[a].next_seq for a in streams})
    return trainer, streams


class LearnerLoop:
    """Stream ordering, training, acks, weights, checkpoints and status of one learner incarnation."""

    def __init__(self, trainer: Trainer, streams: StreamTable, publisher: Publisher, *, learner_id: str,
                 learner_dir: str | Path, checkpoint_every: int, flag: StopFlag,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """:param trainer: the model and its schedule
        :param streams: the actor streams (empty, or from a checkpoint)
        :param publisher: where acks, weights and status go
        :param learner_id: this learner's id (status)
        :param learner_dir: ``RUN_DIR/learner`` (checkpoints)
        :param checkpoint_every: checkpoint every N ingested transitions (0: only when asked and at the end)
        :param flag: the process's stop flag (a ``stop`` command sets it)
        :param clock: monotonic seconds (status period)
        """
        self.trainer, self.streams, self.pub = trainer, streams, publisher
        self.id = learner_id
        self.dir = Path(learner_dir)
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
        self.touched: set[str] = set()
        self.inbox: _Inbox | None = None
        self.task: TaskDescriptor | None = None  # the run's task: batches of other sizes or tasks are refused
        self.dims = ANY_DIMS
        now = clock()
        self._status_t, self._status_steps = now, trainer.gradient_steps

    # ------------------------------------------------------------------------------------ input
    def receive(self, kind: str, key: str, payload: bytes) -> None:
        """One message as it arrived (``kind`` as filed by the inbox); a bad one is counted and logged.

        :param kind: 'transitions' or 'control'
        :param key: the key expression it arrived on
        :param payload: its bytes
        """
        try:
            if kind == "transitions":
                msg = decode(Transitions, payload, self.dims)
                if msg.actor != Keys.chunk(key, 3):
                    raise ProtocolError(f"actor {msg.actor!r} published on {key}")
                if self.task is not None and msg.task is not None and msg.task != self.task.digest:
                    raise ProtocolError(f"actor {msg.actor} runs a task with digest {msg.task}, this learner was built "
                                        f"for {self.task.name!r} (digest {self.task.digest}): start them with one task")
                self.offer(msg)
            else:
                cmd = decode(Control, payload)
                log.info("control: %s (%s)", cmd.command, key)
                self.control(cmd)
        except ProtocolError as exc:
            self.rejects.reject(kind, key, exc)

    def set_task(self, task) -> None:
        """The run's task descriptor: transitions are checked against its sizes and digest, acks carry its digest.

        :param task: a :class:`~common.descriptor.TaskDescriptor`
        """
        self.task = task
        self.dims = Dims(obs=task.obs_dim, out=task.out_dim)

    def _ack(self, actor: str) -> Ack:
        ack = self.trainer.ack(self.streams[actor])
        return ack if self.task is None else ack.replace(task=self.task.digest)

    def offer(self, msg: Transitions) -> str:
        """A decoded batch: ordered into its actor's stream and, when accepted, stored (with any batches it
        unblocked). Returns 'accepted', 'duplicate' or 'held'; the actor is acked at the next :meth:`step`.

        :param msg: the batch
        """
        res = self.streams.offer(msg)
        for batch in res.ready:
            self.trainer.add(batch, res.stream, self.streams.positions)
        self.results[res.result] += 1
        self.touched.add(msg.actor)
        return res.result

    def control(self, msg: Control) -> None:
        """A decoded control command: stop, checkpoint, pause or resume training.

        :param msg: the command
        """
        if msg.command == "stop":
            self.flag.set("stop command")
        elif msg.command == "checkpoint":
            self.checkpoint_requested = True
        elif msg.command in ("pause", "resume"):
            self.paused = msg.command == "pause"

    def drain(self, inbox: _Inbox) -> int:
        """Take up to :data:`MAX_DRAIN` messages (waiting briefly for the first when there is nothing to train).

        :param inbox: a :class:`common.transport.Inbox` (items ``(kind, key, payload, arrival)``)
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
        for actor in self.streams:
            self.pub.ack(self._ack(actor))

    def ack_touched(self) -> None:
        """Ack the actors whose batches arrived since the last call."""
        for actor in sorted(self.touched):
            self.pub.ack(self._ack(actor))
        self.touched.clear()

    def step(self) -> None:
        """After messages were taken in: ack, then :meth:`work`."""
        self.ack_touched()
        self.work()

    def work(self) -> None:
        """Train one due iteration (unless paused), checkpoint when due, publish status when its time has come."""
        if not self.paused and self.trainer.due:
            self.train()
        every = self.checkpoint_every
        if self.checkpoint_requested or (every > 0 and self.trainer.total - self.last_ckpt_total >= every):
            self.checkpoint_requested = False
            self.checkpoint()
        if self.clock() - self._status_t >= STATUS_EVERY_S:
            self.publish_status()

    def train(self) -> bool:
        """One due training iteration, then the new weights and acks for every actor."""
        t0 = time.perf_counter()
        if not self.trainer.train_one():
            return False
        dt = time.perf_counter() - t0
        self.train_time += dt
        self.pub.weights(self.trainer.weights())
        self.ack_all()
        self.trainer.record_iteration(dt, self.queue_depth())
        return True

    def checkpoint(self) -> Path:
        """Save a checkpoint of everything accepted so far, then tell every actor (``durable`` in the acks)."""
        t0 = time.perf_counter()
        tr = self.trainer
        path = save_checkpoint(self.dir, tr.model, {**tr.state(), **self.streams.state()})
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
                           weights_queries=int(self.pub.queries))

    def publish_status(self) -> None:
        """Publish :meth:`info` as this learner's status."""
        self.pub.status(Status(role="learner", info=self.info()))

    # ------------------------------------------------------------------------------------ the loop
    def run(self, inbox: _Inbox) -> None:
        """Turn until the stop flag is set (SIGINT/SIGTERM or a ``stop`` command). The caller checkpoints last.

        :param inbox: where the Zenoh callbacks file transitions and control messages
        """
        self.inbox = inbox
        while not self.flag:
            self.drain(inbox)
            self.ack_touched()
            if self.flag:
                break
            self.work()

    def summary(self) -> dict[str, Any]:
        """Totals for the log line at the end."""
        tr = self.trainer
        return {"transitions": tr.total, "iterations": tr.iterations, "gradient_steps": tr.gradient_steps,
                "train_s": round(self.train_time, 1), "version": tr.version, "rejected": self.rejects.by_kind(),
                "offers": dict(self.results)}
