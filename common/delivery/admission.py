"""The learner's per-sender budget (:class:`Admission`), checked in the Zenoh callback before a batch is copied out of
Zenoh, decoded, its ``mac`` and signature checked or its actor id looked up: one id's flood of valid, cheap batches
costs the other actors the callback's few microseconds per batch, not the learner's decoding, checking and
training time (docs/attacks.md, issue 34 point 7).

Each sender (the actor id in the key a batch came on, :func:`~khgrl.common.delivery.senders.owner`) has two token
buckets, of batches and of payload bytes. Members -- ids whose batches the learner has stored -- get
:data:`MEMBER_BURST` batches (:data:`MEMBER_BURST_BYTES`) refilling at :data:`MEMBER_RATE` a second
(:data:`MEMBER_BYTES_PER_S`); other ids :data:`GUEST_BURST` batches refilling at :data:`GUEST_RATE`. A batch
accepted in order gives its tokens back (:meth:`Admission.refund`): an honest actor, whose batches are accepted
in order, never runs dry however fast it steps; what it spends is on re-sends and batches that were not in order.
An honest actor has at most its window (64 batches by default) out beyond what was acked, within a member's burst.

A batch over its sender's budget is refused (counted in the learner's rejects as ``over_budget``, logged at a
bounded rate). A member is then *over budget* for :data:`PENALTY_S` seconds (:meth:`Admission.penalized`): the
learner stores nothing of it and drops what it holds for it (the held and deferred batches: an honest sender
re-sends them), so a flood gets no share of training -- without this the batches let through by the refill, in
order, were stored up to the lead cap and trained on like an honest actor's, which is what slowed the honest
actor (a0 waits for the learner). A sender that stays within its budget is a member like any other: it may store
as much as flow control lets an actor (its fair share of training).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Callable

__all__ = ["Admission", "TokenBucket", "MEMBER_BURST", "MEMBER_RATE", "MEMBER_BURST_BYTES", "MEMBER_BYTES_PER_S",
           "GUEST_BURST", "GUEST_RATE", "GUEST_BURST_BYTES", "GUEST_BYTES_PER_S", "PENALTY_S", "MAX_SENDERS"]

MEMBER_BURST = 256  # batches at once (an honest actor: its window, 64 by default, at most)
MEMBER_RATE = 20.0  # batches a second, besides the refunds of batches accepted in order
MEMBER_BURST_BYTES = 160 * 2**20  # bytes at once (more than 64 batches of the largest size a batch may have)
MEMBER_BYTES_PER_S = 4 * 2**20
GUEST_BURST = 64  # an id not stored yet: its first window
GUEST_RATE = 10.0
GUEST_BURST_BYTES = 64 * 2**20
GUEST_BYTES_PER_S = 2 * 2**20
PENALTY_S = 2.0  # after a refusal, the sender stores nothing for this long
MAX_SENDERS = 4096  # senders with a bucket; beyond, the one seen least recently (not a member) is forgotten


class TokenBucket:
    """Batches and bytes, refilled by the second up to a burst.

    :param burst: batches at once
    :param rate: batches a second
    :param burst_bytes: bytes at once (a full bucket takes one batch of any size: its bytes may go below 0)
    :param bytes_per_s: bytes a second
    :param now: the time it starts full at
    """

    __slots__ = ("burst", "rate", "burst_bytes", "bytes_per_s", "tokens", "bytes", "t")

    def __init__(self, burst: float, rate: float, burst_bytes: float, bytes_per_s: float, now: float) -> None:
        self.burst, self.rate, self.burst_bytes, self.bytes_per_s = burst, rate, burst_bytes, bytes_per_s
        self.tokens, self.bytes, self.t = float(burst), float(burst_bytes), now

    def take(self, size: int, now: float) -> bool:
        """Whether a batch of ``size`` bytes fits now (then it is spent).

        :param size: its payload bytes
        :param now: monotonic seconds
        """
        dt, self.t = max(0.0, now - self.t), now
        self.tokens = min(self.burst, self.tokens + dt * self.rate)
        self.bytes = min(self.burst_bytes, self.bytes + dt * self.bytes_per_s)
        if self.tokens >= 1.0 and (self.bytes >= size or self.bytes >= self.burst_bytes):  # (full: any one batch)
            self.tokens -= 1.0
            self.bytes -= size
            return True
        return False

    def give(self, size: int) -> None:
        """A batch of ``size`` bytes back (up to the burst).

        :param size: its payload bytes
        """
        self.tokens = min(self.burst, self.tokens + 1.0)
        self.bytes = min(self.burst_bytes, self.bytes + size)


class Admission:
    """Per-sender budgets (see the module docstring). Called from Zenoh's threads (:meth:`admit`) and the ingest
    thread (:meth:`refund`, :meth:`penalized`): one lock, a few dictionary operations a call.

    :param member: whether an id is a member (the learner has stored batches of it)
    :param on_refused: called with ``(sender, size)`` for each batch refused (the learner counts and logs it)
    :param clock: monotonic seconds
    """

    def __init__(self, member: Callable[[str], bool], on_refused: Callable[[str, int], None] | None = None, *,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.member, self.on_refused, self.clock = member, on_refused, clock
        self.buckets: OrderedDict[str, tuple[TokenBucket, bool]] = OrderedDict()  # sender -> (bucket, member's)
        self.refused_at: dict[str, float] = {}  # sender -> when its last batch was refused
        self.refused = 0
        self._lock = threading.Lock()

    def _bucket(self, sender: str, now: float) -> TokenBucket:
        entry = self.buckets.get(sender)
        member = self.member(sender)
        if entry is None or (member and not entry[1]):  # (a guest that became a member starts a member's bucket)
            bucket = TokenBucket(MEMBER_BURST, MEMBER_RATE, MEMBER_BURST_BYTES, MEMBER_BYTES_PER_S, now) if member \
                else TokenBucket(GUEST_BURST, GUEST_RATE, GUEST_BURST_BYTES, GUEST_BYTES_PER_S, now)
            if entry is not None:  # (what it had spent stays spent)
                bucket.tokens = min(bucket.tokens, entry[0].tokens + bucket.burst - entry[0].burst)
            self.buckets[sender] = (bucket, member)
            self._forget()
        else:
            self.buckets.move_to_end(sender)
        return self.buckets[sender][0]

    def _forget(self) -> None:
        """Keep at most :data:`MAX_SENDERS` buckets (the least recently seen non-members go first)."""
        if len(self.buckets) <= MAX_SENDERS:
            return
        for sender, (_, member) in list(self.buckets.items()):
            if not member:
                del self.buckets[sender]
                self.refused_at.pop(sender, None)
                if len(self.buckets) <= MAX_SENDERS:
                    return

    def admit(self, sender: str, size: int) -> bool:
        """Whether a batch of ``sender`` of ``size`` payload bytes may be taken in (then its tokens are spent);
        a refused one is counted and reported to ``on_refused``.

        :param sender: the actor id in the key it came on
        :param size: its payload bytes
        """
        with self._lock:
            now = self.clock()
            if self._bucket(sender, now).take(size, now):
                return True
            self.refused += 1
            self.refused_at[sender] = now
        if self.on_refused is not None:
            self.on_refused(sender, size)
        return False

    def refund(self, sender: str, size: int) -> None:
        """A batch of ``sender`` was accepted in order: its tokens come back.

        :param sender: the actor id
        :param size: its payload bytes
        """
        with self._lock:
            entry = self.buckets.get(sender)
            if entry is not None:
                entry[0].give(size)

    def penalized(self, sender: str) -> bool:
        """Whether ``sender`` is a member and a batch of it was refused in the last :data:`PENALTY_S` seconds (then
        the learner stores nothing of it). An id not stored yet is not: what its budget lets through is checked
        as usual (and refused unless valid); once one of its batches is stored it is a member.

        :param sender: the actor id
        """
        with self._lock:
            t = self.refused_at.get(sender)
            if t is None or not self.member(sender):
                return False
            if self.clock() - t < PENALTY_S:
                return True
            del self.refused_at[sender]
            return False
