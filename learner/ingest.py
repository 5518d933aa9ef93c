"""Per-actor ordering of the transition stream: each actor's batches reach the replay buffer exactly once and
in ``seq`` order, whatever order (and however often) they arrive.

A batch with ``seq == next`` is accepted, followed by any held batches that it unblocks; an older one is a
duplicate (the actor re-sent it before our ack reached it: acked again, not stored); a newer one is held in a
bounded table until the actor re-sends the gap. An actor that restarts announces a new ``stream`` id and starts
a new stream (a new provenance code); ``base_seq`` (the oldest batch the actor still holds) lets a learner that
lost its state skip batches nobody holds any more instead of waiting for them forever.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from common.protocol import Transitions

__all__ = ["ActorStream", "StreamTable", "Offer", "MAX_PENDING"]

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
    pending: dict[int, Transitions] = field(default_factory=dict)

    def stored(self, step: int) -> None:
        """One transition of this stream, the actor's transition ``step``, went into the replay buffer.

        :param step: the transition's running index in the actor's stream
        """
        self.ingested += 1
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
    """What became of an offered batch: ``result`` ('accepted', 'duplicate' or 'held') and, in order, the
    batches now ready for the replay buffer (the offered one and those it unblocked; empty unless accepted)."""

    result: str
    stream: ActorStream
    ready: list[Transitions]


class StreamTable:
    """Every actor stream the learner has seen, and the provenance codes of all of them (a restarted actor
    gets a new code, so its old and new transitions stay distinguishable)."""

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

    def _stream_for(self, msg: Transitions) -> ActorStream:
        """The actor's stream; a new one for an actor not seen yet or one that announces a new stream id."""
        a, stream, base = msg.actor, msg.stream or "", msg.base_seq or 0
        st = self.streams.get(a)
        if st is None or (stream and st.stream and stream != st.stream):
            if st is not None:
                log.warning("actor %s restarted (stream %s -> %s): new stream from seq %d", a, st.stream, stream, base)
            st = ActorStream(actor=a, code=len(self.codes), stream=stream, next_seq=base)
            self.codes.append({"actor": a, "stream": stream})
            self.streams[a] = st
        elif stream and not st.stream:
            st.stream = stream
        return st

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
