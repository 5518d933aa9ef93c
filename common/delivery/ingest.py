"""Per-actor ordering of the transition stream: each actor's batches reach the replay buffer exactly once and
in ``seq`` order, whatever order (and however often) they arrive.

A batch with ``seq == next`` is accepted, followed by any held batches that it unblocks; an older one is a
duplicate (the actor re-sent it before our ack reached it: acked again, not stored); a newer one is held in a
bounded table until the actor re-sends the gap. A restarted actor continues its stream (same ``stream`` id,
``seq`` carrying on); a new ``stream`` id for an actor starts a new stream (a new provenance code) and retires
the one before for good: its batches are refused from then on ('superseded', see :class:`StreamTable`), so
two processes with one actor id are never interleaved. ``base_seq`` (the oldest batch the actor still holds)
lets a learner that lost its state skip batches nobody holds any more instead of waiting for them forever.

:class:`FairInbox` takes the learner's messages in per actor (round robin), so that batches of actor ids the
learner has not admitted yet (no stream in the table) cannot starve the admitted ones: they share one slot of
the rotation, at most :data:`PENDING_IDS` of them wait, and new ones are admitted at a bounded rate.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from khgrl.common.delivery.senders import owner
from khgrl.common.wire.protocol import Transitions

__all__ = ["ActorStream", "StreamTable", "Offer", "MAX_PENDING", "FairInbox", "PENDING_IDS", "PENDING_PER_ID"]

log = logging.getLogger("khgrl.learner")

MAX_PENDING = 4096  # out-of-order batches held per actor; beyond that they are dropped (the actor re-sends them)


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
    pending: dict[int, Transitions] = field(default_factory=dict)

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
        return cls(actor=s["actor"], code=int(s["code"]), stream=s.get("stream", ""), next_seq=int(s["next_seq"]),
                   ingested=int(s["ingested"]), index=int(s.get("index", s["ingested"])), durable=int(s["durable"]),
                   duplicates=int(s.get("duplicates", 0)), skipped=int(s.get("skipped", 0)))


@dataclass(frozen=True)
class Offer:
    """What became of an offered batch: ``result`` ('accepted', 'duplicate', 'held' or 'superseded': a stream
    of the actor that another one replaced) and, in order, the batches now ready for the replay buffer (the
    offered one and those it unblocked; empty unless accepted)."""

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

    def __contains__(self, actor: str) -> bool:
        return actor in self.streams

    def __getitem__(self, actor: str) -> ActorStream:
        return self.streams[actor]

    def __iter__(self):
        return iter(self.streams)

    def positions(self) -> dict[str, int]:
        """Each actor's running index after its last stored transition."""
        return {a: st.index for a, st in self.streams.items()}

    def offer(self, msg: Transitions) -> Offer:
        """Order one decoded batch into its actor's stream.

        :param msg: the batch (its ``envelope.seq`` is the batch number)
        """
        st = self._stream_for(msg)
        if st is None:
            return Offer("superseded", self.streams[msg.actor], [])
        seq = msg.envelope.seq
        self._skip_to(st, msg.base_seq or 0)
        if seq < st.next_seq:
            st.duplicates += 1
            return Offer("duplicate", st, [])
        if seq > st.next_seq:
            self._hold(st, seq, msg)
            return Offer("held", st, [])
        ready = [msg]
        st.next_seq += 1
        while st.next_seq in st.pending:
            ready.append(st.pending.pop(st.next_seq))
            st.next_seq += 1
        return Offer("accepted", st, ready)

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

    @staticmethod
    def _skip_to(st: ActorStream, base: int) -> None:
        """The actor holds nothing before ``base``: stop waiting for those batches."""
        if base <= st.next_seq:
            return
        log.error("actor %s no longer holds batches %d..%d (confirmed durable by an earlier learner): skipping them",
                  st.actor, st.next_seq, base - 1)
        st.skipped += base - st.next_seq
        st.next_seq = base
        for s in [s for s in st.pending if s < base]:
            del st.pending[s]

    @staticmethod
    def _hold(st: ActorStream, seq: int, msg: Transitions) -> None:
        """Keep a batch that arrived before the gap in front of it was filled (bounded)."""
        if seq in st.pending:
            return
        if len(st.pending) >= MAX_PENDING:
            st.dropped_pending += 1  # the actor re-sends it
            return
        st.pending[seq] = msg
        st.held += 1

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


PENDING_IDS = 64  # actor ids not admitted yet whose batches wait; batches of further new ids are dropped
PENDING_PER_ID = 64  # batches that wait per such id (the actor re-sends what was dropped)
ADMIT_PER_S = 10.0  # new actor ids admitted per second (after a burst of ADMIT_BURST)
ADMIT_BURST = 32
PULL_MAX = 20_000  # messages moved from the inbox into the per-actor queues per call
_PENDING = "\0pending"  # the one rotation slot that all not-yet-admitted ids share


class FairInbox:
    """The learner's inbox, served per actor: each admitted actor takes turns (one batch each), and all actor ids
    not admitted yet share one turn. Taking messages out of the inbox is cheap (no decoding), so a backlog of
    other ids' batches never stands in front of an admitted actor's. A not-yet-admitted id is admitted when the
    loop takes its first batch (which makes its stream); at most ``admit_per_s`` new ids are, after a burst.
    A control message keeps its place: it is served once the batches that arrived before it are (and nothing
    after it is taken in before). Same interface as :class:`khgrl.common.delivery.transport.Inbox` for :meth:`get` and
    :meth:`qsize`.

    :param inbox: where the Zenoh callbacks file ``(kind, key, payload, arrival)``
    :param admitted: whether an actor id is admitted (the learner has its stream)
    :param admit_per_s: new ids admitted per second
    :param clock: monotonic seconds
    """

    def __init__(self, inbox, admitted: Callable[[str], bool], *, admit_per_s: float = ADMIT_PER_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.inbox, self.admitted, self.clock = inbox, admitted, clock
        self.rate = float(admit_per_s)
        self.tokens, self._t = float(ADMIT_BURST), clock()
        self.queues: dict[str, deque] = {}  # admitted actor id -> its batches
        self.pending: dict[str, deque] = {}  # not-yet-admitted actor id -> messages (oldest id first)
        self.turns: deque[str] = deque()  # slots with messages, in the order they are served
        self.barrier: tuple | None = None  # a control message, served when the batches before it are
        self.buffered = 0
        self.dropped = 0  # batches of not-yet-admitted ids dropped (over the caps)

    def qsize(self) -> int:
        """Messages waiting here and in the inbox."""
        return self.buffered + self.inbox.qsize()

    def get(self, timeout: float = 0.0) -> tuple | None:
        """The next message by turn, waiting up to ``timeout`` s for one to arrive when none waits.

        :param timeout: seconds to wait (0: don't)
        """
        self._pull()
        item = self._next()
        if item is None and timeout > 0:
            if self.barrier is not None:  # waits for ids to be admitted: don't spin
                time.sleep(min(timeout, 0.02))
                return self._next()
            first = self.inbox.get(timeout)
            if first is not None:
                self._file(first)
                self._pull()
                item = self._next()
        return item

    def _pull(self) -> None:
        """Take in what has arrived, up to the next control message."""
        for _ in range(PULL_MAX):
            if self.barrier is not None:
                return
            item = self.inbox.get(0.0)
            if item is None:
                return
            self._file(item)

    def _file(self, item: tuple) -> None:
        """Put one message in its queue (or drop it: a not-yet-admitted id over the caps)."""
        if item[0] != "transitions":
            self.barrier = item
            self.buffered += 1
            return
        slot = owner(item[1])
        q = self.pending.get(slot)
        if q is not None or (slot not in self.queues and not self.admitted(slot)):
            if (q is None and len(self.pending) >= PENDING_IDS) or (q is not None and len(q) >= PENDING_PER_ID):
                self.dropped += 1
                if self.dropped == 1 or self.dropped % 1000 == 0:
                    log.warning("batches of actor ids not admitted yet: %d dropped (%d ids wait)", self.dropped,
                                len(self.pending))
                return
            if not self.pending:
                self.turns.append(_PENDING)
            self.pending.setdefault(slot, deque()).append(item)
        else:
            q = self.queues.get(slot)
            if q is None:
                q = self.queues[slot] = deque()
                self.turns.append(slot)
            q.append(item)
        self.buffered += 1

    def _next(self) -> tuple | None:
        if self.barrier is not None and self.buffered == 1:  # every batch that came before it is served
            item, self.barrier = self.barrier, None
            self.buffered -= 1
            return item
        for _ in range(len(self.turns) + 1):  # (+1: an id that the pending turn moved to its own turn)
            if not self.turns:
                return None
            slot = self.turns.popleft()
            item = self._from_pending() if slot == _PENDING else self._from_queue(slot)
            if slot == _PENDING and self.pending:
                self.turns.append(_PENDING)
            if item is not None:
                self.buffered -= 1
                return item
        return None

    def _from_queue(self, slot: str) -> tuple:
        q = self.queues[slot]
        item = q.popleft()
        if q:
            self.turns.append(slot)
        else:
            del self.queues[slot]
        return item

    def _from_pending(self) -> tuple | None:
        """The oldest waiting id's next batch, if a new id may be admitted now (ids admitted meanwhile first
        move to their own turn)."""
        for actor in [a for a in self.pending if self.admitted(a)]:
            self.queues[actor] = self.pending.pop(actor)
            self.turns.append(actor)
        if not self.pending:
            return None
        now = self.clock()
        self.tokens = min(float(ADMIT_BURST), self.tokens + (now - self._t) * self.rate)
        self._t = now
        if self.tokens < 1.0:
            return None
        self.tokens -= 1.0
        actor = next(iter(self.pending))
        q = self.pending[actor]
        item = q.popleft()
        if not q:
            del self.pending[actor]
        return item
