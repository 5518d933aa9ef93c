"""The actor's side of the transition stream to the learner: cut batches, keep them until durable, read
acks, re-send what the learner may have missed (docs/protocol.md, "Transitions and acks").

Batches are numbered ``seq`` 0, 1, 2, ... and kept in an :class:`~actor.outbox.Outbox` until an ack says
``durable >= seq``. Everything after ``ack.received`` is re-sent when the ack's epoch changes (learner
restarted), shortly after the learner's liveliness token appears, or when un-acked data has waited more
than ``resend_after_s`` without progress. Re-sent batches carry the current ``base_seq`` (the oldest batch
still held) so a learner that never saw this actor starts there. An ack that claims more than this actor has
sent is refused (counted and logged): it must not make the actor drop batches the learner does not hold.

No Zenoh here: batches go out through the ``publish`` callable (tests pass a list's ``append``).
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

from actor.outbox import Outbox
from common.messages import Ack, Transitions
from common.protocol import encode, with_base_seq
from common.wire import ProtocolError, RejectCounter

__all__ = ["TransitionStream", "LEARNER_APPEARED_RESEND_S", "CHECKPOINT_REQUEST_EVERY_S"]

log = logging.getLogger("khgrl.actor")

LEARNER_APPEARED_RESEND_S = 0.3  # a learner that appeared without acking gets the outbox re-sent after this
CHECKPOINT_REQUEST_EVERY_S = 5.0  # at the end, ask the learner for a checkpoint at most this often


class TransitionStream:
    """Collects one actor's transitions and delivers them exactly once (with the learner's help).

    :param actor: the actor id.
    :param stream: random id of this actor incarnation (acks for another stream are not for us).
    :param outbox: where batches wait until durable.
    :param publish: sends one encoded ``transitions`` payload.
    :param rejects: counts refused acks.
    :param resend_after_s: re-send un-acked batches after this long without ack progress.
    :param clock: monotonic clock (tests pass a fake one).
    :param task: the digest of the actor's task descriptor (the learner refuses batches of another task).
    """

    def __init__(self, actor: str, stream: str, outbox: Outbox, publish: Callable[[bytes], None],
                 rejects: RejectCounter, resend_after_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, task: str | None = None) -> None:
        self.actor = actor
        self.task = task  # the digest of this actor's task descriptor, stamped on every batch
        self.stream = stream
        self.outbox = outbox
        self.publish = publish
        self.rejects = rejects
        self.resend_after_s = float(resend_after_s)
        self.clock = clock
        self.count = 0  # transitions collected (the next transition's per-actor index)
        self.sent = 0  # transitions published (first time)
        self.next_seq = 0
        self._buf: list[tuple] = []
        self._buf_first = 0
        # what the learner told us
        self.ack_epoch: str | None = None
        self.received = -1
        self.durable = -1
        self.trained = 0
        self.ack_version = 0
        self.last_progress = clock()
        self.resend_at: float | None = None
        self.checkpoint_requested_at = -1e9
        self.resends = 0
        self.resent_batches = 0
        self.refused_acks = 0

    @property
    def highest_sent(self) -> int:
        """The highest seq published so far (-1: none)."""
        return self.next_seq - 1

    # ------------------------------------------------------------------ collecting
    def add(self, obs, next_obs, action, reward: float, terminated: bool, truncated: bool, intervened: bool,
            clipped: bool) -> None:
        """Collect one transition (it goes out with the next :meth:`cut`).

        :param obs: observation before the step.
        :param next_obs: observation after it.
        :param action: the stored action (the human's a_h when intervened).
        :param reward: the step's reward.
        :param terminated: episode ended (goal or failure).
        :param truncated: episode ended at the horizon.
        :param intervened: a human correction drove the step.
        :param clipped: the human action was clipped to [-1, 1].
        """
        self._buf.append((obs, next_obs, action, reward, terminated, truncated, intervened, clipped))
        self.count += 1

    def cut(self) -> None:
        """Publish what was collected since the last cut as one batch (nothing if empty)."""
        if not self._buf:
            return
        cols = list(zip(*self._buf))
        seq = self.next_seq
        oldest = self.outbox.oldest()
        batch = Transitions(
            actor=self.actor, first_step=self._buf_first,
            obs=np.asarray(cols[0], dtype=np.float32), next_obs=np.asarray(cols[1], dtype=np.float32),
            action=np.asarray(cols[2], dtype=np.float32), reward=np.asarray(cols[3], dtype=np.float32),
            terminated=np.asarray(cols[4], dtype=np.uint8), truncated=np.asarray(cols[5], dtype=np.uint8),
            intervened=np.asarray(cols[6], dtype=np.uint8), clipped=np.asarray(cols[7], dtype=np.uint8),
            base_seq=seq if oldest is None else oldest, stream=self.stream, task=self.task)
        payload = encode(batch, self.actor, seq)
        newest = self.outbox.newest()
        if newest is None or newest <= self.received:
            self.last_progress = self.clock()  # nothing was waiting: the resend timer starts now
        self.outbox.add(seq, payload, len(self._buf))
        self.publish(payload)
        self.next_seq += 1
        self.sent += len(self._buf)
        self._buf = []
        self._buf_first = self.count

    # ------------------------------------------------------------------ acks
    def on_ack(self, ack: Ack, key: str = "ack") -> bool:
        """Take in an ack; returns whether it was for this stream and believable.

        :param ack: a decoded ack.
        :param key: the key it came on (for the reject log).
        """
        # the learner echoes the stream id of the transitions it acks; an ack without it is not for us
        if ack.actor != self.actor or ack.stream != self.stream:
            return False
        if ack.received > self.highest_sent or ack.durable > self.highest_sent:
            self.refused_acks += 1
            # one fixed reason, so that a flood of forged acks costs a few log lines (RejectCounter: the first,
            # then every 100th)
            self.rejects.reject("ack", key, ProtocolError("ack claims batches beyond the highest seq sent"))
            return False
        new_epoch = ack.epoch != self.ack_epoch
        restarted = new_epoch and self.ack_epoch is not None
        if restarted:
            log.info("learner epoch changed (%s -> %s): received %d, durable %d", self.ack_epoch, ack.epoch,
                     ack.received, ack.durable)
            self.checkpoint_requested_at = -1e9
        if ack.received > self.received or new_epoch:
            self.last_progress = self.clock()
        self.ack_epoch = ack.epoch
        self.received = ack.received
        self.trained = ack.trained
        self.ack_version = ack.version
        if ack.durable > self.durable or new_epoch:
            self.durable = max(self.durable, ack.durable)
            self.outbox.drop_through(self.durable)
        if restarted:
            self.resend_at = None
            self.resend(self.received, "new learner epoch")
        return True

    def learner_appeared(self) -> None:
        """A learner's liveliness token appeared. A resumed learner acks at once with its new epoch (which
        re-sends); a fresh one only acks what it receives: re-send the whole outbox shortly unless that ack
        came first."""
        now = self.clock()
        self.resend_at = now + LEARNER_APPEARED_RESEND_S
        self.last_progress = now  # (that re-send replaces the stall timer's)

    def check_resend(self, learner_alive: bool) -> None:
        """Re-send if a learner appeared a moment ago, or un-acked batches have waited too long.

        :param learner_alive: whether a learner's liveliness token is present.
        """
        now = self.clock()
        if self.resend_at is not None and now >= self.resend_at:
            self.resend_at = None
            self.resend(-1, "learner appeared")
        newest = self.outbox.newest()
        if learner_alive and newest is not None and newest > self.received \
                and now - self.last_progress > self.resend_after_s:
            self.resend(self.received, "no ack progress for %.1f s" % (now - self.last_progress))

    def resend(self, after: int, why: str) -> None:
        """Publish again every batch held above ``after``, stamped with the current ``base_seq``.

        :param after: exclusive lower bound (the learner's ``received``; -1: everything held).
        :param why: for the log.
        """
        seqs = self.outbox.seqs_after(after)
        self.last_progress = self.clock()
        if not seqs:
            return
        base = self.outbox.oldest()
        for s in seqs:
            self.publish(with_base_seq(self.outbox.get(s), base))
        self.resends += 1
        self.resent_batches += len(seqs)
        log.info("re-sent batches %d..%d (%d) after %d: %s", seqs[0], seqs[-1], len(seqs), after, why)

    def checkpoint_due(self, learner_alive: bool) -> bool:
        """At the end: whether to ask the learner for a checkpoint now (it holds everything, none asked lately).

        :param learner_alive: whether a learner's liveliness token is present.
        """
        now = self.clock()
        if learner_alive and self.received >= self.highest_sent \
                and now - self.checkpoint_requested_at > CHECKPOINT_REQUEST_EVERY_S:
            self.checkpoint_requested_at = now
            return True
        return False

    def all_durable(self) -> bool:
        """Every batch sent is in a learner checkpoint."""
        return self.durable >= self.highest_sent

    def unconfirmed(self) -> int:
        """Transitions sent but not yet confirmed durable."""
        return self.outbox.transitions_after(self.durable)

    def summary(self) -> dict:
        """This stream's part of ``summary.json``."""
        return {"transitions": self.count, "sent": self.sent, "batches": self.next_seq, "last_seq": self.highest_sent,
                "received": self.received, "durable": self.durable, "unconfirmed_transitions": self.unconfirmed(),
                "outbox_spilled": self.outbox.spilled_total, "resends": self.resends,
                "resent_batches": self.resent_batches, "refused_acks": self.refused_acks}
