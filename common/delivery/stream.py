"""The actor's side of the transition stream to the learner: cut batches, keep them until durable, read
acks, re-send what the learner may have missed (docs/protocol.md, "Transitions and acks").

Batches are numbered ``seq`` 0, 1, 2, ... and kept in an :class:`~khgrl.common.delivery.outbox.Outbox` until an ack says
``durable >= seq``. Flow control is a window: at most ``window`` batches beyond what the learner acknowledged
(``received``) are out at a time; later batches wait in the outbox and go as acks come in. Sending goes from a
cursor, which is moved back to just after ``received`` (so only the window is re-sent) when the ack's epoch
changes (learner restarted), to the oldest held batch shortly after the learner's liveliness token appears, and
to after ``received`` when un-acked data has waited ``resend_after_s`` without ack progress -- then twice as
long, up to :data:`MAX_RESEND_AFTER_S`, until acks move again. Re-sent or held-back batches carry the current
``base_seq`` (the oldest batch still held) so a learner that never saw this actor starts there. An ack that
claims more than this actor has published is refused (counted and logged): it must not make the actor drop
batches the learner does not hold; so is one the caller's ``check`` finds implausible (a weights version far above
any seen).

A stream outlives its process: a restarted actor continues it (:mod:`khgrl.common.delivery.restart`) with the ``seq``,
running
index and durable point of the earlier process, and an outbox re-read from disk that it re-sends shortly after
the start. Before batch files are deleted as durable, the stream's position goes to its ``journal`` (the
record in ``stream.json``). An ack that says the stream was *superseded* (the learner admitted another stream
of this actor id) makes :attr:`TransitionStream.superseded` say why; the loop then stops.

No Zenoh here: batches go out through the ``publish`` callable (tests pass a list's ``append``).

One module of ~340 lines on purpose: one class, the actor's side of the stream, whose cutting, keeping and re-
sending share the same batches.
"""

from __future__ import annotations

import logging
import time
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np
from khgrl.common.delivery import data_keys
from khgrl.common.delivery.camera_rows import batch_arrays, row_limit, state_of
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.vouching import evidence
from khgrl.common.wire.bounds import check_bounds, limits
from khgrl.common.wire.checks import ProtocolError, RejectCounter
from khgrl.common.wire.messages import Ack, Transitions
from khgrl.common.wire.protocol import encode, with_base_seq

__all__ = ["TransitionStream", "LEARNER_APPEARED_RESEND_S", "CHECKPOINT_REQUEST_EVERY_S", "MAX_RESEND_AFTER_S"]

log = logging.getLogger("khgrl.actor")

LEARNER_APPEARED_RESEND_S = 0.3  # a learner that appeared without acking gets the outbox re-sent after this
CHECKPOINT_REQUEST_EVERY_S = 5.0  # at the end, ask the learner for a checkpoint at most this often
MAX_RESEND_AFTER_S = 30.0  # the stall timer's backoff stops here


class TransitionStream:
    """Collects one actor's transitions and delivers them exactly once (with the learner's help).

    :param actor: the actor id.
    :param stream: random id of this actor incarnation (acks for another stream are not for us).
    :param outbox: where batches wait until durable.
    :param publish: sends one encoded ``transitions`` payload.
    :param rejects: counts refused acks.
    :param resend_after_s: re-send un-acked batches after this long without ack progress (then backing off).
    :param clock: monotonic clock (tests pass a fake one).
    :param task: the digest of the actor's task descriptor (the learner refuses batches of another task).
    :param next_seq: the seq of the next batch (a continued stream: where the earlier process stopped).
    :param next_index: the running index of the next transition (likewise).
    :param durable: the highest seq the learner confirmed durable (likewise).
    :param journal: called with :meth:`position` before batch files are deleted as durable.
    :param window: batches out beyond the learner's ``received`` at most.
    :param key: the run's key or the actor's :class:`~khgrl.common.delivery.data_keys.DataKeys`: every batch
        sent carries its ``mac`` and (with a role key) its ``actor:<id>`` signature, a re-stamped one is signed again
        (None: neither).
    """

    def __init__(self, actor: str, stream: str, outbox: Outbox, publish: Callable[[bytes], None],
                 rejects: RejectCounter, resend_after_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, task: str | None = None, *, next_seq: int = 0,
                 next_index: int = 0, durable: int = -1, journal: Callable[[dict], None] | None = None,
                 window: int = 64, key: data_keys.Keyish = None) -> None:
        self.actor = actor
        self.key = key
        self.task = task  # the digest of this actor's task descriptor, stamped on every batch
        self.stream = stream
        self.outbox = outbox
        self.publish = publish
        self.rejects = rejects
        self.resend_after_s = float(resend_after_s)
        self.clock = clock
        self.start_index = int(next_index)  # the running index this process started at (0 unless continued)
        self.count = self.start_index  # the next transition's running index in the stream
        self.sent = self.start_index  # the running index after the last transition published (first time)
        self.next_seq = int(next_seq)
        self.window = max(1, int(window))
        self.cursor = self.next_seq  # the next seq to publish
        self.max_published = self.next_seq - 1  # (a continued stream's earlier process published the rest)
        self.stalls = 0  # stall re-sends since the last ack progress (the backoff's exponent)
        self._buf: list[tuple] = []
        self._words: list[Any] = []  # per collected transition, what drove it (vouching.evidence)
        self._buf_first = self.start_index
        self.journal = journal
        self.superseded: str | None = None  # why the learner no longer takes this stream
        # what the learner told us
        self.ack_epoch: str | None = None
        self.received = -1
        self.durable = int(durable)
        self.trained = 0
        self.ack_version = 0
        self.last_progress = clock()
        self.resend_at: float | None = None
        self.checkpoint_requested_at = -1e9
        self.resends = 0
        self.resent_batches = 0
        self.refused_acks = 0
        self.bounds: Any = None  # the task descriptor whose value bounds a transition must keep to be sent (None: any)
        self.out_of_bounds = 0  # transitions not sent: a value outside the task's bounds (the learner refuses them)
        self._limits: tuple | None = None  # (bounds, obs low, obs high, reward bound), computed once per bounds
        self.rows: int | None = None  # rows per batch at most (0: the caller's cuts only; camera observations: set)
        if len(outbox):  # batches an earlier process left: re-send them all shortly (as to a new learner)
            self.resend_at = clock() + LEARNER_APPEARED_RESEND_S

    @property
    def highest_sent(self) -> int:
        """The highest seq published so far (-1: none)."""
        return self.next_seq - 1

    def position(self) -> dict:
        """Where the stream stands (the fields of :class:`~.restart.StreamRecord` but ``stream``)."""
        return {"next_seq": self.next_seq, "next_index": self._buf_first, "durable": self.durable}

    # ------------------------------------------------------------------ collecting
    def add(self, obs, next_obs, action, reward: float, terminated: bool, truncated: bool, intervened: bool,
            clipped: bool, word: Any = None) -> None:
        """Collect one transition (it goes out with the next :meth:`cut`).

        :param obs: observation before the step (a camera task's: its Dict, :mod:`~.camera_rows`).
        :param next_obs: observation after it.
        :param action: the stored action (the human's a_h when intervened).
        :param reward: the step's reward.
        :param terminated: episode ended (goal or failure).
        :param truncated: episode ended at the horizon.
        :param intervened: a human correction drove the step.
        :param clipped: the human action was clipped to [-1, 1].
        :param word: what drove an intervened step: the signed correction (its evidence goes out in the batch's
            ``vouch``), :data:`~khgrl.common.delivery.vouching.DEMO` for a demonstration, None (no evidence).
        """
        if self.bounds is not None and self._out_of_bounds(state_of(obs), state_of(next_obs), action, reward):
            return
        self._buf.append((obs, next_obs, action, reward, terminated, truncated, intervened, clipped))
        self._words.append(word if intervened else None)
        self.count += 1
        if self.rows is None:
            self.rows = row_limit(obs) or 0
        if self.rows and len(self._buf) >= self.rows:  # a camera batch's frames: within the wire's limit
            self.cut()

    def _out_of_bounds(self, obs, next_obs, action, reward: float) -> bool:
        """Whether a transition holds a value the learner would refuse (not finite, outside the task's bounds: a
        sensor glitch, say); it is then not sent -- a batch holding it would be refused whole and never acked, and the
        actor would wait for that ack for ever -- but counted (``out_of_bounds`` in the summary) and logged."""
        if self._limits is None or self._limits[0] is not self.bounds:
            lim = limits(self.bounds, np.size(obs))
            self._limits = (self.bounds, *lim["obs"], lim["reward"][1])
        _, low, high, reward_bound = self._limits
        if -reward_bound <= reward <= reward_bound and ((obs >= low) & (obs <= high)).all() and \
                ((next_obs >= low) & (next_obs <= high)).all():  # (the usual case: NaN compares false)
            return False
        row = SimpleNamespace(obs=np.reshape(obs, (1, -1)), next_obs=np.reshape(next_obs, (1, -1)),
                              action=np.reshape(action, (1, -1)), reward=np.reshape(np.float32(reward), (1,)))
        why = check_bounds(row, self.bounds)  # (the reason, as the learner would give it)
        if why is None:
            return False
        self.out_of_bounds += 1
        if self.out_of_bounds in (1, 10) or self.out_of_bounds % 1000 == 0:
            log.error("actor %s: transition %d not sent (%d so far): %s", self.actor, self.count, self.out_of_bounds,
                      why)
        return True

    def cut(self) -> None:
        """Publish what was collected since the last cut as one batch (nothing if empty)."""
        if not self._buf:
            return
        cols = list(zip(*self._buf))
        seq = self.next_seq
        oldest = self.outbox.oldest()
        done = np.logical_or(cols[4], cols[5])
        batch = Transitions(
            actor=self.actor, first_step=self._buf_first, **batch_arrays(cols[0], cols[1], done),
            action=np.asarray(cols[2], dtype=np.float32), reward=np.asarray(cols[3], dtype=np.float32),
            terminated=np.asarray(cols[4], dtype=np.uint8), truncated=np.asarray(cols[5], dtype=np.uint8),
            intervened=np.asarray(cols[6], dtype=np.uint8), clipped=np.asarray(cols[7], dtype=np.uint8),
            base_seq=seq if oldest is None else oldest, stream=self.stream, task=self.task,
            vouch=tuple(e for i, w in enumerate(self._words) if (e := evidence(i, w)) is not None) or None)
        payload = encode(data_keys.sign_batch(batch, self.key, seq), self.actor, seq)
        newest = self.outbox.newest()
        if newest is None or newest <= self.received:
            self.last_progress = self.clock()  # nothing was waiting: the resend timer starts now
        self.outbox.add(seq, payload, len(self._buf))
        self.next_seq += 1
        self._buf, self._words = [], []
        self._buf_first = self.count
        if self.cursor == seq and self._in_window(seq):
            self._send(seq, payload)  # the usual case: straight out, as encoded
        else:
            self.pump()

    def _in_window(self, seq: int) -> bool:
        return seq <= max(self.received, self.durable) + self.window

    def _send(self, seq: int, payload: bytes) -> None:
        self.publish(payload)
        self.cursor = seq + 1
        if seq > self.max_published:
            self.max_published = seq
            self.sent += self.outbox.sizes.get(seq, 0)
        else:
            self.resent_batches += 1

    def pump(self) -> int:
        """Publish from the cursor up to the window's end (re-stamped with the current ``base_seq``); returns how
        many batches went out."""
        oldest = self.outbox.oldest()
        if oldest is None:
            self.cursor = self.next_seq
            return 0
        self.cursor = max(self.cursor, oldest)
        key, n = self.key, 0
        sign = None if key is None else lambda m: data_keys.wire_sign(m, key)  # re-stamped: signed again
        while self.cursor < self.next_seq and self._in_window(self.cursor):
            self._send(self.cursor, with_base_seq(self.outbox.get(self.cursor), oldest, sign))
            n += 1
        return n

    # ------------------------------------------------------------------ acks
    def on_ack(self, ack: Ack, key: str = "ack", check: Callable[[Ack], str | None] | None = None) -> bool:
        """Take in an ack; returns whether it was for this stream and believable.

        :param ack: a decoded ack.
        :param key: the key it came on (for the reject log).
        :param check: says why an ack for this stream cannot be true (None: it can), beyond the seq check here
            (the actor's :meth:`~khgrl.common.delivery.trust.WeightsGate.implausible` weights version).
        """
        # the learner echoes the stream id of the transitions it acks; an ack without it is not for us
        if ack.actor != self.actor or ack.stream != self.stream:
            return False
        if ack.superseded:
            if self.superseded is None:
                self.superseded = (f"the learner took another stream of actor {self.actor} after this one (stream "
                                   f"{self.stream}): another process runs this actor id")
                log.error("%s", self.superseded)
            return False
        if ack.received > self.max_published or ack.durable > self.max_published:
            self.refused_acks += 1
            # one fixed reason, so that a flood of forged acks costs a few log lines (RejectCounter: the first,
            # then every 100th)
            self.rejects.reject("ack", key, ProtocolError("ack claims batches beyond the highest seq sent"))
            return False
        why = check(ack) if check is not None else None
        if why:
            self.refused_acks += 1
            self.rejects.reject("ack", key, ProtocolError(f"ack: {why}"))
            return False
        new_epoch = ack.epoch != self.ack_epoch
        restarted = new_epoch and self.ack_epoch is not None
        if restarted:
            log.info("learner epoch changed (%s -> %s): received %d, durable %d", self.ack_epoch, ack.epoch,
                     ack.received, ack.durable)
            self.checkpoint_requested_at = -1e9
        if ack.received > self.received or new_epoch:
            self.last_progress = self.clock()
            self.stalls = 0
        self.ack_epoch = ack.epoch
        self.received = ack.received
        self.trained = ack.trained
        self.ack_version = ack.version
        if ack.durable > self.durable or new_epoch:
            self.durable = max(self.durable, ack.durable)
            oldest = self.outbox.oldest()
            if self.journal is not None and oldest is not None and oldest <= self.durable:
                self.journal(self.position())  # first the record, then the files go
            self.outbox.drop_through(self.durable)
        if restarted:
            self.resend_at = None
            self.resend(self.received, "new learner epoch")
        elif self.cursor < self.next_seq:
            self.cursor = max(self.cursor, self.received + 1)
            self.pump()  # the window moved: what waited goes
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
        wait = min(self.resend_after_s * 2 ** self.stalls, MAX_RESEND_AFTER_S)
        if learner_alive and newest is not None and newest > self.received and now - self.last_progress > wait:
            self.stalls += 1
            self.resend(self.received, "no ack progress for %.1f s" % (now - self.last_progress))

    def resend(self, after: int, why: str) -> None:
        """Send again from the batch after ``after``: the window's worth now, the rest as acks come in.

        :param after: exclusive lower bound (the learner's ``received``; -1: everything held).
        :param why: for the log.
        """
        self.last_progress = self.clock()
        self.cursor = after + 1
        first = max(self.cursor, self.outbox.oldest() if self.outbox.oldest() is not None else self.next_seq)
        n = self.pump()
        if not n:
            return
        self.resends += 1
        log.info("re-sent batches %d..%d (%d) after %d: %s", first, self.cursor - 1, n, after, why)

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
        return {"transitions": self.count - self.start_index, "sent": self.sent - self.start_index,
                "first_index": self.start_index, "next_index": self.count, "batches": self.next_seq,
                "last_seq": self.highest_sent,
                "received": self.received, "durable": self.durable, "unconfirmed_transitions": self.unconfirmed(),
                "outbox_spilled": self.outbox.spilled_total, "resends": self.resends,
                "resent_batches": self.resent_batches, "refused_acks": self.refused_acks,
                "out_of_bounds": self.out_of_bounds}
