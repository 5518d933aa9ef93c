"""Per-actor ordering of the transition stream: each actor's batches reach the replay buffer exactly once and
in ``seq`` order, whatever order (and however often) they arrive.

A batch with ``seq == next`` is accepted, followed by any held batches that it unblocks; an older one is a
duplicate (the actor re-sent it before our ack reached it: acked again, not stored); a newer one is held in a
bounded table until the actor re-sends the gap. A restarted actor continues its stream (same ``stream`` id,
``seq`` carrying on); a new ``stream`` id for an actor starts a new stream (a new provenance code) and retires
the one before for good: its batches are refused from then on ('superseded', see :class:`StreamTable`), so
two processes with one actor id are never interleaved. ``base_seq`` (the oldest batch the actor still holds)
lets a learner that lost its state skip batches nobody holds any more instead of waiting for them forever.

Shares: :meth:`StreamTable.offer` and :meth:`StreamTable.release` take the ``room`` the learner gives an actor
(transitions it may store now, see :class:`~khgrl.common.delivery.learner_side.LearnerIngest`): a batch in order
that does not fit is *deferred* -- kept with the held ones, neither stored nor acked -- and released when the room
has grown. Held and deferred batches are capped in bytes per actor (:data:`PENDING_BYTES_PER_ACTOR`) and over all
actors (:data:`PENDING_BYTES_TOTAL`); what is over the caps is dropped and counted (the actor re-sends it).

:class:`FairInbox` (:mod:`khgrl.common.delivery.fair_inbox`, re-exported here) takes the learner's messages in per
actor (round robin), so that batches of actor ids the learner has not admitted yet cannot starve the admitted ones.

One module of ~320 lines on purpose: the per-actor stream and the table of streams share one ordering rule (exactly
once, in ``seq`` order) that a reader checks in one place.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from khgrl.common.delivery.fair_inbox import PENDING_IDS, PENDING_PER_ID, FairInbox
from khgrl.common.wire.protocol import Transitions

__all__ = ["ActorStream", "StreamTable", "Offer", "MAX_PENDING", "FairInbox", "PENDING_IDS", "PENDING_PER_ID",
           "PENDING_BYTES_PER_ACTOR", "PENDING_BYTES_TOTAL", "batch_bytes"]

log = logging.getLogger("khgrl.learner")

MAX_PENDING = 4096  # out-of-order batches held per actor; beyond that they are dropped (the actor re-sends them)
# Bytes of held (out of order) and deferred (over the actor's room) batches. An honest actor has at most its window
# (default 64) batches out beyond what was acked: 64 batches of 8 transitions are tens of kB, and even 64 batches of
# 64 transitions of a 100-dimensional observation are 3.4 MB. 16 MiB is four maximum-size batches (4,096
# transitions of a 240-dimensional observation each), so an honest actor is never cut, while 4,096 held maximum-size
# batches (1.1 GB measured before this cap) are not possible. The total bounds many actor ids together: 128 MiB.
PENDING_BYTES_PER_ACTOR = 16 * 2**20
PENDING_BYTES_TOTAL = 128 * 2**20


def batch_bytes(msg: Transitions) -> int:
    """The bytes of a batch's arrays (what holding it costs).

    :param msg: the batch
    """
    return sum(int(a.nbytes) for a in (msg.obs, msg.next_obs, msg.action, msg.reward, msg.terminated, msg.truncated,
                                       msg.intervened, msg.clipped))


@dataclass
class ActorStream:
    """What the learner knows about one actor's transition stream."""

    actor: str
    code: int  # provenance code: index into StreamTable.codes
    stream: str = ""  # the actor incarnation (the transitions' optional ``stream`` field)
    next_seq: int = 0  # the next batch seq to accept
    ingested: int = 0  # transitions stored from this stream
    index: int = 0  # the actor's running index after the last stored transition (== ingested unless the stream
    # was adopted mid-way by a learner without a checkpoint, see base_seq)
    durable: int = -1  # highest seq held in a checkpoint
    duplicates: int = 0
    held: int = 0
    dropped_pending: int = 0
    skipped: int = 0  # batches the actor no longer holds (see base_seq): lost, logged
    superseded: int = 0  # batches of earlier streams of this actor id refused since this stream began
    deferred: int = 0  # in-order batches kept back because they did not fit the actor's room
    pending: dict[int, Transitions] = field(default_factory=dict)
    pending_bytes: int = 0  # bytes of the batches in ``pending``
    # the learner's count of this stream's transitions that trained weights cover (see LearnerIngest.lead): marks
    # are (running index after a stored batch, never decreasing; ``ingested`` then) not yet covered
    covered: int = 0
    marks: deque = field(default_factory=deque)
    mark_index: int = 0

    def stored(self, step: int, n: int = 1) -> None:
        """``n`` transitions of this stream, the last being the actor's transition ``step``, went into the replay
        buffer.

        :param step: the last one's running index in the actor's stream
        :param n: how many
        """
        self.ingested += n
        self.index = step + 1

    def state(self) -> dict[str, Any]:
        """The stream's position for a checkpoint (held batches are not kept: the actor re-sends them)."""
        return {"actor": self.actor, "code": self.code, "stream": self.stream, "next_seq": self.next_seq,
                "ingested": self.ingested, "index": self.index, "durable": self.durable, "duplicates": self.duplicates,
                "skipped": self.skipped}

    @classmethod
    def from_state(cls, s: dict[str, Any]) -> "ActorStream":
        """A stream as saved by :meth:`state`.

        :param s: the saved map
        """
        ingested = int(s["ingested"])  # (all of it counts as covered: the resumed learner trains what is due)
        return cls(actor=s["actor"], code=int(s["code"]), stream=s.get("stream", ""), next_seq=int(s["next_seq"]),
                   ingested=ingested, index=int(s.get("index", s["ingested"])), durable=int(s["durable"]),
                   duplicates=int(s.get("duplicates", 0)), skipped=int(s.get("skipped", 0)), covered=ingested,
                   mark_index=int(s.get("index", s["ingested"])))

    def mark(self) -> None:
        """After a stored batch: note how many transitions this stream has in, against its running index (a rewound
        index does not lower the mark, so rewinding never makes stored transitions look trained)."""
        self.mark_index = max(self.mark_index, self.index)
        self.marks.append((self.mark_index, self.ingested))

    def lead(self, trained: int) -> int:
        """Transitions stored from this stream that no trained weights cover yet.

        :param trained: the stream's running index the latest weights cover (its ack's ``trained``)
        """
        while self.marks and self.marks[0][0] <= trained:
            self.covered = self.marks.popleft()[1]
        return self.ingested - self.covered


@dataclass(frozen=True)
class Offer:
    """What became of an offered batch: ``result`` ('accepted', 'duplicate', 'held', 'deferred': in order but over
    the actor's room, 'dropped': over the pending caps, or 'superseded': a stream of the actor that another one
    replaced) and, in order, the batches now ready for the replay buffer (the offered one and those it unblocked;
    empty unless accepted)."""

    result: str
    stream: ActorStream
    ready: list[Transitions]


class StreamTable:
    """Every actor stream the learner has seen, and the provenance codes of all of them (an actor with a new
    stream id gets a new code, so its old and new transitions stay distinguishable). An actor's current stream
    is the newest one: the earlier streams of that actor id (those in :attr:`codes`) are refused."""

    def __init__(self) -> None:
        self.streams: dict[str, ActorStream] = {}
        self.codes: list[dict[str, str]] = []  # provenance code -> {"actor", "stream"}
        self.pending_bytes = 0  # held and deferred batches, all actors
        self.dropped_pending = 0  # batches dropped over the pending caps, all actors
        self.skipped = 0  # batches skipped (no actor holds them any more: lost), all actors, since counting began
        # (a resumed learner counts from the end of its journal replay)
        self.journal_loss: Any = None  # a resumed learner: the confirmed batches its journal lost (JournalLoss)

    def __contains__(self, actor: str) -> bool:
        return actor in self.streams

    def __getitem__(self, actor: str) -> ActorStream:
        return self.streams[actor]

    def __iter__(self):
        return iter(self.streams)

    def positions(self) -> dict[str, int]:
        """Each actor's running index after its last stored transition."""
        return {a: st.index for a, st in self.streams.items()}

    def offer(self, msg: Transitions, room: Callable[[ActorStream], int | None] | None = None) -> Offer:
        """Order one decoded batch into its actor's stream.

        :param msg: the batch (its ``envelope.seq`` is the batch number)
        :param room: transitions the batch's stream may store now (None, or a None answer: no limit); a batch in
            order that does not fit is deferred
        """
        st = self._stream_for(msg)
        if st is None:
            return Offer("superseded", self.streams[msg.actor], [])
        seq = msg.envelope.seq
        self._skip_to(st, msg.base_seq or 0)
        if seq < st.next_seq:
            st.duplicates += 1
            return Offer("duplicate", st, [])
        free = room(st) if room is not None else None
        if seq > st.next_seq or (free is not None and msg.n > free):
            kept = self._hold(st, seq, msg)
            if seq == st.next_seq and kept:
                st.deferred += 1
            return Offer(("deferred" if seq == st.next_seq else "held") if kept else "dropped", st, [])
        st.next_seq += 1
        return Offer("accepted", st, [msg] + self._unblocked(st, None if free is None else free - msg.n))

    def release(self, actor: str, room: int | None) -> list[Transitions]:
        """The actor's held batches that are now in order and fit ``room`` (taken out of pending, in order).

        :param actor: the actor id
        :param room: transitions its stream may store now (None: no limit)
        """
        st = self.streams[actor]
        return self._unblocked(st, room) if st.next_seq in st.pending else []

    def _unblocked(self, st: ActorStream, room: int | None) -> list[Transitions]:
        ready = []
        while st.next_seq in st.pending and (room is None or st.pending[st.next_seq].n <= room):
            msg = self._unhold(st, st.next_seq)
            ready.append(msg)
            st.next_seq += 1
            room = None if room is None else room - msg.n
        return ready

    def _stream_for(self, msg: Transitions) -> ActorStream | None:
        """The actor's stream; a new one for an actor not seen yet or one that announces a new stream id; None for
        a stream of the actor that was replaced by a newer one."""
        a, stream, base = msg.actor, msg.stream or "", msg.base_seq or 0
        st = self.streams.get(a)
        if st is None or (stream and st.stream and stream != st.stream):
            if st is not None and self.retired(a, stream):
                st.superseded += 1
                if st.superseded == 1 or st.superseded % 1000 == 0:
                    log.error("actor %s: batch of stream %s refused: the learner took stream %s of this actor id after "
                              "it (two processes with one id?); %d refused", a, stream, st.stream, st.superseded)
                return None
            if st is not None:
                log.warning("actor %s: new stream %s replaces stream %s (from seq %d); the old one is refused from now "
                            "on", a, stream, st.stream, base)
            if st is not None:  # its held batches go with it
                self.pending_bytes -= st.pending_bytes
            st = ActorStream(actor=a, code=len(self.codes), stream=stream, next_seq=base)
            self.codes.append({"actor": a, "stream": stream})
            self.streams[a] = st
        elif stream and not st.stream:
            st.stream = stream
        return st

    def retired(self, actor: str, stream: str) -> bool:
        """Whether ``stream`` is an earlier stream of ``actor`` (one the learner took before the current one).

        :param actor: the actor id
        :param stream: a stream id
        """
        cur = self.streams.get(actor)
        return bool(stream) and (cur is None or cur.stream != stream) and \
            any(c["actor"] == actor and c["stream"] == stream for c in self.codes)

    def _skip_to(self, st: ActorStream, base: int) -> None:
        """The actor holds nothing before ``base``: stop waiting for those batches."""
        if base <= st.next_seq:
            return
        log.error("actor %s no longer holds batches %d..%d (confirmed durable by an earlier learner): skipping them",
                  st.actor, st.next_seq, base - 1)
        st.skipped += base - st.next_seq
        self.skipped += base - st.next_seq
        st.next_seq = base
        for s in [s for s in st.pending if s < base]:
            self._unhold(st, s)

    def _hold(self, st: ActorStream, seq: int, msg: Transitions) -> bool:
        """Keep a batch that arrived before the gap in front of it was filled, or that does not fit the actor's room
        yet (bounded in batches and bytes, per actor and in all); whether it is kept (False: dropped, counted)."""
        if seq in st.pending:
            return True
        size = batch_bytes(msg)
        if len(st.pending) >= MAX_PENDING or st.pending_bytes + size > PENDING_BYTES_PER_ACTOR \
                or self.pending_bytes + size > PENDING_BYTES_TOTAL:
            st.dropped_pending += 1  # the actor re-sends it
            self.dropped_pending += 1
            if self.dropped_pending == 1 or self.dropped_pending % 1000 == 0:
                log.warning("actor %s: batch %d not held (%d kB held for it, %d kB in all: over the caps); %d dropped",
                            st.actor, seq, st.pending_bytes // 1024, self.pending_bytes // 1024, self.dropped_pending)
            return False
        st.pending[seq] = msg
        st.pending_bytes += size
        self.pending_bytes += size
        st.held += 1
        return True

    def drop_held(self, actor: str) -> int:
        """Drop every batch held or deferred for ``actor`` (counted as dropped: the actor re-sends what it still
        needs); how many.

        :param actor: the actor id
        """
        st = self.streams.get(actor)
        if st is None or not st.pending:
            return 0
        n = len(st.pending)
        for seq in list(st.pending):
            self._unhold(st, seq)
        st.dropped_pending += n
        self.dropped_pending += n
        return n

    def _unhold(self, st: ActorStream, seq: int) -> Transitions:
        msg = st.pending.pop(seq)
        size = batch_bytes(msg)
        st.pending_bytes -= size
        self.pending_bytes -= size
        return msg

    def state(self) -> dict[str, Any]:
        """Codes and stream positions for a checkpoint (``durable``: what this checkpoint will hold)."""
        return {"codes": list(self.codes),
                "actors": {a: dict(st.state(), durable=st.next_seq - 1) for a, st in self.streams.items()}}

    def mark_durable(self) -> None:
        """A checkpoint holding everything accepted so far is on disk."""
        for st in self.streams.values():
            st.durable = st.next_seq - 1

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> "StreamTable":
        """The table as saved by :meth:`state`.

        :param state: a checkpoint's state map (``codes`` and ``actors``)
        """
        table = cls()
        table.codes = [dict(c) for c in state["codes"]]
        table.streams = {a: ActorStream.from_state(dict(s, actor=a)) for a, s in state["actors"].items()}
        return table
