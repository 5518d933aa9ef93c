"""Two bounds of the learner's receiving side (:class:`~khgrl.common.delivery.learner_side.LearnerIngest`) against
peers that hold a valid actor identity but misuse it:

* :class:`ReplayGuard` -- a batch whose content (every array) is identical to one stored recently from another
  actor id is not stored again (a peer republishing another actor's batches under its own id);
* :class:`RequestLimiter` -- checkpoint requests on ``actor/<id>/request`` are honoured only from actor ids whose
  batches the learner has stored, at most one per :data:`REQUEST_EVERY_S` per actor, and turned into at most one
  checkpoint per :data:`REQUEST_GAP_S` in all (requests meanwhile are merged into the next one, never lost).
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from typing import Callable

import numpy as np
from khgrl.common.wire.protocol import Transitions

__all__ = ["ReplayGuard", "RequestLimiter", "batch_digest", "REPLAY_TABLE", "REQUEST_EVERY_S", "REQUEST_GAP_S"]

REPLAY_TABLE = 65_536  # digests of the most recently stored batches (16 B each; ~8 MB with the table's overhead):
# at the default 8 transitions a batch, 524,288 transitions, more than the replay buffer holds (200,000)
REQUEST_EVERY_S = 2.0  # an actor asks at most every 5 s (stream.CHECKPOINT_REQUEST_EVERY_S): more is refused
REQUEST_GAP_S = 1.0  # checkpoints asked for by actors: at most one per this (requests meanwhile wait for it)
# the arrays a batch's digest covers: all but ``intervened`` (setting or clearing the flag does not make a replay new)
_ARRAYS = ("obs", "next_obs", "action", "reward", "terminated", "truncated", "clipped")


def batch_digest(msg: Transitions) -> bytes:
    """A 16-byte BLAKE2b digest of a batch's content: its arrays (shapes, dtypes and bytes) but ``intervened``, not
    its envelope, actor id, ``seq``, ``first_step``, stream or ``vouch`` evidence. About 2.5 ms per 4 MiB batch
    (docs/protocol.md, "Trust model").

    :param msg: the batch
    """
    h = hashlib.blake2b(digest_size=16)
    for name in _ARRAYS:
        a = getattr(msg, name)
        h.update(f"{name}{a.dtype.str}{a.shape}".encode())
        h.update(np.ascontiguousarray(a))
    return h.digest()


class ReplayGuard:
    """The digests of the last ``size`` batches stored, from any stream, and by which actor id: a batch seen there
    from another actor id is a replay. (The same actor id may send the same content again: a restarted actor that
    starts a fresh stream repeats its seeded warm-up steps.)

    Two honest actors produce byte-identical batches when a human drove every step of them the same way: a
    scripted human in a deterministic world corrects two actors identically (measured: 8 batches of a two-actor
    run). Such a batch -- every transition vouched for by a human's signed correction
    (:mod:`~khgrl.common.delivery.vouching`; the flag alone is the sender's word) -- is therefore never taken for a
    replay. A batch with a
    step of the policy differs between actors (each samples its actions with its own seed: actors ``a<i>`` get
    ``seed + i``, other ids a seed made from the id), so an identical one from another id is a replay: it is not
    stored, but its stream moves on as if it were (it is acked), so nothing waits.

    :param size: how many digests are kept (oldest forgotten first)
    """

    def __init__(self, size: int = REPLAY_TABLE) -> None:
        self.size = int(size)
        self.seen: OrderedDict[bytes, str] = OrderedDict()  # digest -> the actor that stored it
        self.replayed = 0

    def check(self, msg: Transitions, vouched: bool | None = None) -> tuple[bytes, str | None]:
        """The batch's digest, and the other actor id that stored the same content recently (None: none did).

        :param msg: the batch
        :param vouched: whether a human vouched for every row (None: every row flagged ``intervened``, a run without
            role keys)
        """
        digest = batch_digest(msg)
        if np.all(msg.intervened) if vouched is None else vouched:  # (human-driven steps may repeat: the class)
            return digest, None
        first = self.seen.get(digest)
        return digest, None if first == msg.actor else first

    def stored(self, digest: bytes, actor: str) -> None:
        """A batch with this digest went into the replay buffer.

        :param digest: :func:`batch_digest` of it
        :param actor: its actor id
        """
        self.seen[digest] = actor
        if len(self.seen) > self.size:
            self.seen.popitem(last=False)


class RequestLimiter:
    """Which checkpoint requests of actors the learner honours, and when (see the module docstring).

    :param admitted: whether the learner has stored batches of an actor id
    :param every_s: per actor, the least time between two honoured requests
    :param gap_s: the least time between two checkpoints asked for by actors
    :param clock: monotonic seconds
    """

    def __init__(self, admitted: Callable[[str], bool], *, every_s: float = REQUEST_EVERY_S,
                 gap_s: float = REQUEST_GAP_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.admitted, self.every_s, self.gap_s, self.clock = admitted, float(every_s), float(gap_s), clock
        self.last: dict[str, float] = {}  # admitted actor -> when its last request was taken
        self.last_checkpoint = -float("inf")
        self.waiting = False  # a taken request waits for the gap to pass

    def refuse(self, actor: str) -> str | None:
        """Why a checkpoint request of ``actor`` is refused (None: it is taken: :meth:`due` says when to act on it).

        :param actor: the requesting actor id (the request key's ``<id>``, equal to the message's sender)
        """
        if not self.admitted(actor):
            return "checkpoint request from an actor id whose batches the learner has not stored"
        now = self.clock()
        if now - self.last.get(actor, -float("inf")) < self.every_s:
            return f"checkpoint request: more than one per {self.every_s:g} s from this actor"
        self.last[actor] = now
        self.waiting = True
        return None

    def due(self) -> bool:
        """Whether to ask for a checkpoint now: a request was taken and the last one asked for is far enough back."""
        now = self.clock()
        if not self.waiting or now - self.last_checkpoint < self.gap_s:
            return False
        self.waiting, self.last_checkpoint = False, now
        return True
