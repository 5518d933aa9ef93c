"""The learner's receiving side: what arrives from the actors, decoded and checked
(:func:`~khgrl.common.delivery.senders.read_for_learner`), ordered into each actor's stream
(:class:`~khgrl.common.delivery.ingest.StreamTable`: accepted, duplicate, held or superseded), handed to the trainer
in order, and acknowledged. :meth:`LearnerIngest.start` runs it on its own *ingest thread*, which takes messages as
they arrive -- served per actor (:class:`~khgrl.common.delivery.ingest.FairInbox`) -- and never waits for a gradient
step; the learner loop trains on the calling thread and shares :attr:`LearnerIngest.lock` with it (streams,
counters and acks), and :attr:`LearnerIngest.wake` tells it that there may be something to train.

Shares (docs/protocol.md, "Trust model"): with a :attr:`LearnerIngest.lead_cap` (simulation mode) an actor's batches
are stored only while the transitions of its stream that no trained weights cover yet stay within that cap -- what
flow control lets an honest actor have out (``max_lead`` plus a batch) -- and the rest is deferred until training
catches up, so an actor cannot queue more than ``lead_cap / train_freq`` training iterations ahead of the others'.
A batch larger than the cap can never fit: it is dropped (``rejects.over_lead``). A batch whose content was stored
recently (from any stream) is not stored again (``rejects.replayed``,
:class:`~khgrl.common.delivery.guards.ReplayGuard`),
and checkpoint requests are limited (:class:`~khgrl.common.delivery.guards.RequestLimiter`).

Unit tests drive it in one thread: :meth:`LearnerIngest.offer` with decoded batches, or
:meth:`LearnerIngest.receive` with payload bytes.

One module of ~360 lines on purpose: one class, the learner's receiving side, whose steps (decode, check, order,
store, ack) share one lock and one set of counters.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from typing import Any, Callable, Protocol

from khgrl.common.delivery import data_keys
from khgrl.common.delivery.admission import Admission
from khgrl.common.delivery.batch_conflicts import SignedSeqs
from khgrl.common.delivery.control_auth import ControlGate
from khgrl.common.delivery.guards import ReplayGuard, RequestLimiter
from khgrl.common.delivery.ingest import ActorStream, FairInbox, StreamTable
from khgrl.common.delivery.learner_link import Publisher
from khgrl.common.delivery.senders import owner, read_for_learner
from khgrl.common.delivery.vouching import Vouching, demo_rows
from khgrl.common.wire.bounds import check_bounds
from khgrl.common.wire.checks import ProtocolError, RejectCounter
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import Ack, Control, Dims, Transitions
from khgrl.common.wire.protocol import ANY_DIMS, attribute_control

__all__ = ["LearnerIngest", "MAX_DRAIN", "IDLE_WAIT_S"]

log = logging.getLogger("khgrl.learner")

MAX_DRAIN = 512  # messages taken in a row before the ingest thread acks what they brought
IDLE_WAIT_S = 0.05  # how long the ingest thread (and an idle learner loop) waits for something to arrive


class _Inbox(Protocol):
    def get(self, timeout: float = 0.0) -> tuple | None: ...

    def qsize(self) -> int: ...


class LearnerIngest:
    """Decodes, checks, orders, stores (through ``store``) and acks the actors' batches; hands control commands to
    ``on_control``.

    :param streams: the actor streams (empty, or from a checkpoint)
    :param publisher: where acks go
    :param store: called with ``(batch, stream, positions)`` for each batch accepted in order (the trainer's ``add``)
    :param ack_of: the ack of an actor stream as the trainer sees it (trained, version, epoch)
    :param on_control: a control command (``stop``, ``checkpoint``, ``pause``, ``resume``)
    :param learner_id: this learner's id (rejects)
    :param flag: the process's stop flag (the ingest thread runs until it is set, and sets it if it fails)
    :param key: the run's key or :class:`~khgrl.common.delivery.data_keys.DataKeys`: batches without its
        ``mac`` or (with role keys) their actor's signature are refused before they are stored or their actor id
        admitted (None: none checked)
    """

    def __init__(self, streams: StreamTable, publisher: Publisher, *, store: Callable[..., None],
                 ack_of: Callable[[Any], Ack], on_control: Callable[[Control], None], learner_id: str, flag,
                 key: data_keys.Keyish = None) -> None:
        self.streams, self.pub, self.store, self.ack_of, self.on_control = streams, publisher, store, ack_of, on_control
        self.flag, self.key = flag, key
        self.control = ControlGate.of_run(None)  # who may send control (set to the run's: its role keys)
        self.rejects = RejectCounter(f"learner/{learner_id}")
        self.results: Counter = Counter()  # offers by result
        self.touched: set[str] = set()
        self.inbox: Any = None
        self.task: TaskDescriptor | None = None  # the run's task: batches of other sizes or tasks are refused
        self.dims: Dims = ANY_DIMS
        self.lock = threading.RLock()  # streams, counters and acks between the ingest and training threads
        self.wake = threading.Event()  # set when there may be something to train
        self.lead_cap: int | None = None  # transitions of an actor not yet covered by trained weights (None: no cap)
        self.replay = ReplayGuard()
        self.vouching = Vouching(key.public if data_keys.checking(key) else None)  # intervened rows need a human
        self.signed = SignedSeqs()  # (actor, stream, seq) -> what its actor signed: a second, different one alarms
        self.requests = RequestLimiter(self.admitted)
        self.admission = Admission(self.admitted, self._over_budget)  # per-sender budgets, before decoding

    def admitted(self, actor: str) -> bool:
        """Whether the learner has stored batches of ``actor`` (its current stream).

        :param actor: an actor id
        """
        st = self.streams.streams.get(actor)
        return st is not None and st.ingested > 0

    def _over_budget(self, sender: str, size: int) -> None:
        """A batch refused by :attr:`admission` (in a Zenoh callback): counted and logged (rate-limited)."""
        self.rejects.reject("over_budget", f"actor/{sender}/transitions", ProtocolError(
            f"actor {sender}: batches over its budget (refused before decoding; nothing of it is stored while it "
            f"floods)"))

    def _flooding(self, sender: str) -> None:
        """A batch let through by the budget of a sender that is over it (one of its batches was refused just now:
        :meth:`~khgrl.common.delivery.admission.Admission.penalized`): not decoded, and what is held for that sender
        is dropped, so that a flood gets no share of training (the sender re-sends what it still needs)."""
        with self.lock:
            self.results["over_budget"] += 1
            self.streams.drop_held(sender)
        self._over_budget(sender, 0)

    def admit(self, key: str, size: int) -> bool:
        """The transitions subscriber's gate: whether a batch on ``key`` of ``size`` bytes is within its sender's
        budget (:class:`~khgrl.common.delivery.admission.Admission`).

        :param key: the key it came on
        :param size: its payload bytes
        """
        return self.admission.admit(owner(key), size)

    def set_task(self, task: TaskDescriptor, teacher_demos: int = 0) -> None:
        """The run's task descriptor: batches are checked against its sizes and digest, acks carry its digest.

        :param task: the descriptor
        :param teacher_demos: demonstrations a0's scripted teacher records first (prior data, like the task's)
        """
        self.task = task
        self.dims = Dims.of_task(task)
        self.vouching.demo_limit = demo_rows(task, teacher_demos)

    # ------------------------------------------------------------------------------------ input
    def receive(self, kind: str, key: str, payload: bytes) -> None:
        """One message as it arrived (``kind`` as filed by the inbox); a bad one is counted and logged.

        :param kind: 'transitions', 'control' (``control/learner``, ``control/all``) or 'request' (a ``control``
            message on ``actor/<id>/request``: only ``checkpoint`` from that actor is taken there)
        :param key: the key expression it arrived on
        :param payload: its bytes

        With the run's key (:attr:`key`) a batch without its right ``mac`` is refused, counted as ``mac``; a batch
        with a value out of the task's bounds (:func:`~khgrl.common.wire.bounds.check_bounds`) is refused whole,
        counted as ``values`` in the rejects.
        """
        if kind == "transitions" and self.admission.penalized(owner(key)):
            self._flooding(owner(key))
            return
        try:
            msg = read_for_learner(kind, key, payload, self.dims, self.task)
        except ProtocolError as exc:
            self.rejects.reject("control" if kind == "request" else kind, key, exc)
            return
        if isinstance(msg, Transitions):
            if self._take(msg, key) == "accepted":
                self.admission.refund(owner(key), len(payload))
            return
        if kind == "control":
            if why := self.control.check(msg, key):  # (unsigned, not the operator's, a replay)
                self.rejects.reject("control", key, ProtocolError(why))
                return
            attribute_control(msg, key, log)
        elif kind == "request":  # only checkpoint requests from their own actor get here (read_for_learner)
            with self.lock:
                why = self.requests.refuse(owner(key))
            if why:
                self.rejects.reject("control", key, ProtocolError(why))
            self.forward_request()
            return
        self.on_control(msg)

    def _take(self, msg: Transitions, key: str) -> str:
        """A decoded batch: refused (counted, rate-limited log) without the right ``mac`` when this learner has the
        run's key -- before it is stored or its actor id admitted -- or with a value out of the task's bounds;
        otherwise :meth:`offer` ed. Returns what became of it ('refused', or :meth:`offer`'s answer).

        :param msg: the batch
        :param key: the key it came on
        """
        seq = msg.envelope.seq
        for kind, check in (("mac", data_keys.check_mac), ("sig", data_keys.check_sig)):
            why = check(msg, self.key)
            if why is not None:
                self.rejects.reject(kind, key, ProtocolError(f"actor {msg.actor} batch {seq}: {why}"))
                return "refused"
        if data_keys.checking(self.key) and (why := self.signed.conflict(msg)) is not None:
            if self.signed.conflicts == 1:
                log.error("%s", why)
            self.rejects.reject("conflict", key, ProtocolError(f"actor {msg.actor} batch {seq}: {why}"))
            return "refused"
        reason = check_bounds(msg, self.task)  # finite, and within the task's value bounds
        if reason is not None:
            self.rejects.reject("values", key, ProtocolError(f"actor {msg.actor} batch {msg.envelope.seq}: {reason}"))
            return "refused"
        return self.offer(msg)

    def forward_request(self) -> None:
        """Hand a taken checkpoint request to ``on_control`` once the gap since the last one has passed."""
        if self.requests.due():
            self.on_control(Control(command="checkpoint"))

    def offer(self, msg: Transitions) -> str:
        """A decoded batch: ordered into its actor's stream and, when accepted, stored (with any batches it
        unblocked). Returns 'accepted', 'duplicate', 'held', 'deferred' (in order, over the actor's room: kept until
        training makes room), 'dropped' (over the held-bytes caps), 'over_lead' (larger than :attr:`lead_cap`) or
        'superseded'; the actor is acked by the next :meth:`ack_touched` (a superseded stream at once, with
        ``superseded`` set: its process stops).

        :param msg: the batch
        """
        with self.lock:
            if self.lead_cap is not None and msg.n > self.lead_cap:
                self.results["over_lead"] += 1
                self.rejects.reject("over_lead", f"actor/{msg.actor}", ProtocolError(
                    f"batch of {msg.n} transitions: more than flow control lets an actor have out ({self.lead_cap})"))
                return "over_lead"
            res = self.streams.offer(msg, self.room)
            self.results[res.result] += 1
            if res.result == "superseded":  # a later stream of this actor id was taken: this one is refused
                self.pub.ack(self.ack(msg.actor).replace(received=-1, durable=-1, trained=0, stream=msg.stream,
                                                         superseded=True))
                return res.result
            if res.result == "dropped":
                self.rejects.reject("pending", f"actor/{msg.actor}", ProtocolError(
                    "batch not held: the actor's held batches are over the learner's byte caps"))
            self._store(res.ready, res.stream)
            self.touched.add(msg.actor)
        if res.ready:
            self.wake.set()
        return res.result

    def room(self, st: ActorStream) -> int | None:
        """Transitions ``st`` may store now: :attr:`lead_cap` less those no trained weights cover (None: no cap).

        :param st: an actor stream
        """
        return None if self.lead_cap is None else self.lead_cap - st.lead(self.ack_of(st).trained)

    def _store(self, batches: list[Transitions], st: ActorStream) -> None:
        """Store batches in order (call with :attr:`lock`); one whose content was stored recently is not (its
        stream moves past it)."""
        for batch in batches:
            verdict = self.vouching.judge(batch)
            digest, first = self.replay.check(batch, verdict.all_vouched if self.vouching.enforced else None)
            if first is not None or verdict.replay_of is not None:
                st.stored(batch.first_step + batch.n - 1, 0)
                self.replay.replayed += 1
                self.results["replayed"] += 1
                what = "identical to one" if first is not None else f"with {verdict.why}: a replay of a batch"
                self.rejects.reject("replayed", f"actor/{batch.actor}", ProtocolError(
                    f"batch {what} of actor {first or verdict.replay_of} stored recently: not stored again"))
                continue
            if verdict.unvouched:
                self.results["unvouched"] += verdict.unvouched
                self.rejects.reject("unvouched", f"actor/{batch.actor}", ProtocolError(
                    f"batch {batch.envelope.seq if batch.envelope else '?'}: {verdict.unvouched} rows flagged "
                    f"intervened without a human's signature ({verdict.why}): stored as ordinary data"))
            self.store(verdict.batch, st, self.streams.positions)
            st.mark()
            self.replay.stored(digest, batch.actor)
            self.vouching.stored(verdict, batch.actor)

    def release(self) -> bool:
        """Store the deferred batches that fit their actors' room now (after training made room); whether any
        was; drop what is held for a sender over its budget (:meth:`_flooding`). Call with :attr:`lock`."""
        if self.lead_cap is None:
            return False
        moved = False
        for st in [st for st in self.streams.streams.values() if st.pending]:
            if self.admission.penalized(st.actor):  # a flood: what it holds goes (see _flooding)
                self.streams.drop_held(st.actor)
                continue
            if st.next_seq not in st.pending:
                continue
            ready = self.streams.release(st.actor, self.room(st))
            if ready:
                self._store(ready, st)
                self.touched.add(st.actor)
                moved = True
        return moved

    # ------------------------------------------------------------------------------------ acks
    def ack(self, actor: str) -> Ack:
        """The ack of ``actor``'s stream now (with the run's task digest)."""
        ack = self.ack_of(self.streams[actor])
        return ack if self.task is None else ack.replace(task=self.task.digest)

    def ack_all(self) -> None:
        """Store what training made room for (:meth:`release`), then ack every known actor stream."""
        with self.lock:
            if self.release():
                self.wake.set()
            for actor in list(self.streams):
                self.pub.ack(self.ack(actor))

    def ack_touched(self) -> None:
        """Ack the actors whose batches arrived since the last call."""
        with self.lock:
            for actor in sorted(self.touched):
                self.pub.ack(self.ack(actor))
            self.touched.clear()

    # ------------------------------------------------------------------------------------ the ingest thread
    def start(self, inbox: _Inbox) -> threading.Thread:
        """Start the ingest thread on ``inbox`` (served per actor); returns it (join it after setting the flag).

        :param inbox: where the Zenoh callbacks file ``(kind, key, payload, arrival)``
            (:class:`~khgrl.common.delivery.learner_link.LearnerLink`)
        """
        fair = self.inbox = FairInbox(inbox, self.streams.__contains__)
        if hasattr(inbox, "gates"):  # (each batch passes its sender's budget before it is copied out of Zenoh)
            inbox.gates["transitions"] = self.admit
        thread = threading.Thread(target=self._run, args=(fair,), name="ingest", daemon=True)
        thread.start()
        return thread

    def _run(self, inbox: _Inbox) -> None:
        """Take in, store and ack what arrives until the stop flag is set."""
        try:
            while not self.flag:
                item = inbox.get(IDLE_WAIT_S)
                n = 0
                while item is not None:
                    self.receive(*item[:3])
                    n += 1
                    item = inbox.get(0.0) if n < MAX_DRAIN else None
                self.ack_touched()
                self.forward_request()
        except Exception:  # noqa: BLE001 - a bug here must stop the learner, not leave it training on nothing
            log.exception("ingest thread failed")
            self.flag.set("ingest thread failed")

    # ------------------------------------------------------------------------------------ status
    def queue_depth(self) -> int:
        """Messages waiting in the inbox (0 when driven without one)."""
        return self.inbox.qsize() if self.inbox is not None else 0

    @property
    def dropped(self) -> int:
        """Messages of actors not yet admitted that the fair inbox dropped."""
        return int(getattr(self.inbox, "dropped", 0))

    def info(self) -> dict[str, Any]:
        """The receiving side's part of the learner's status (call with :attr:`lock` held)."""
        streams = [self.streams[a] for a in self.streams]
        return dict(queue_depth=self.queue_depth(), rejects=self.rejects.by_kind(),
                    next_seq={st.actor: st.next_seq for st in streams},
                    durable={st.actor: st.durable for st in streams},
                    duplicates={st.actor: st.duplicates for st in streams},
                    weights_queries=int(self.pub.queries), not_admitted_dropped=self.dropped, alarm=self.signed.alarm)
