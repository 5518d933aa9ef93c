"""The learner's inbox served per actor (:class:`FairInbox`): batches of actor ids the learner has not admitted yet
(no stream in its table) cannot starve the admitted ones: they share one slot of the rotation, at most
:data:`PENDING_IDS` of them wait, and new ones are admitted at a bounded rate.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import Callable

from khgrl.common.delivery.senders import owner

__all__ = ["FairInbox", "PENDING_IDS", "PENDING_PER_ID", "ADMIT_PER_S", "ADMIT_BURST", "PULL_MAX"]

log = logging.getLogger("khgrl.learner")

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
        self.waiting_new = 0  # of them, batches of ids not admitted yet (in ``pending``)
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
            self.waiting_new += 1
        else:
            q = self.queues.get(slot)
            if q is None:
                q = self.queues[slot] = deque()
                self.turns.append(slot)
            q.append(item)
        self.buffered += 1

    def _next(self) -> tuple | None:
        # every batch of an admitted actor that came before it is served (not those of ids not admitted yet: they
        # trickle in at the admission rate, and a control message -- a checkpoint request, a stop -- is about the
        # admitted streams; a request of an id not admitted is refused anyway)
        if self.barrier is not None and self.buffered - self.waiting_new == 1:
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
            self.waiting_new -= len(self.queues[actor])
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
        self.waiting_new -= 1
        if not q:
            del self.pending[actor]
        return item
