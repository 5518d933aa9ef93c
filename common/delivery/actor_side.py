"""The actor's side of delivery, driven by its control loop between steps (:class:`ActorDelivery`).

* **Inbox**: at most :data:`MAX_SERVICE` messages a step (acks, corrections, commands from Zenoh's ring buffers,
  learner liveliness from the inbox; a flood costs a step a bounded time), each handed to the actor's handler
  (``khgrl.actor.inbound.Inbound``); then the newest admitted weights are swapped in (no stall: a
  ``load_state_dict``; :mod:`~khgrl.common.delivery.trust` says which are admitted), what the learner has not
  acked in time is re-sent (:class:`~khgrl.common.delivery.stream.TransitionStream`), and the actor's status goes
  out about once a second.
* **Flow control** (the window): while the learner is alive, the actor waits while ``sent - ack.trained >=
  max_lead`` or its weights are older than ``ack.version``: the transition about to be collected would otherwise
  make it more than ``max_lead`` transitions ahead of what the learner has trained on. With ``max_lead`` =
  ``batch`` = the train frequency (the defaults) each step is taken with exactly the weights single-process SB3
  would use (those trained at the last multiple of ``train_freq`` after ``learning_starts``). Without a live
  learner, or in ``robot`` mode, the actor acts on with its last weights (a robot does not stop for the learner).
* **The end**: the actor waits until the learner holds every batch in a checkpoint (``flush_timeout``; after a
  stop, :data:`FINISH_WAIT_S`), asking for checkpoints when none comes.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any, Callable

__all__ = ["ActorDelivery", "RateLimitStats", "MAX_SERVICE", "POLL_S", "STATUS_EVERY_S", "FINISH_WAIT_S"]

log = logging.getLogger("khgrl.actor")

MAX_SERVICE = 16  # messages handled per control step at most (a step needs ~2: a correction, an ack)
POLL_S = 0.002  # while waiting for messages: how often the ring buffers are looked at
STATUS_EVERY_S = 1.0
FINISH_WAIT_S = 5.0  # stopped mid-run: how long the actor waits for the learner to checkpoint its last batches


class RateLimitStats:
    """How often and how long the actor waited for the learner (flow control)."""

    def __init__(self) -> None:
        self.waits = 0
        self.wait_s = 0.0


class ActorDelivery:
    """What the actor's loop calls between steps: :meth:`service`, :meth:`rate_limit`, and at the end
    :meth:`flush` or :meth:`finish_on_signal`.

    :param actor: this actor's id
    :param link: its :class:`~khgrl.common.delivery.actor_link.ActorLink`
    :param inbox: where learner liveliness arrives (:class:`~khgrl.common.delivery.transport.Inbox`)
    :param stream: its :class:`~khgrl.common.delivery.stream.TransitionStream`
    :param weights: the policy's weights (``khgrl.actor.weights.PolicyWeights``: ``swap``, ``behind``,
        ``load_replies``, ``version``, ``last_query``)
    :param settings: the run's stream settings (``max_lead``, ``mode``, ``flush_timeout``, ``learner_wait``)
    :param flag: the process's stop flag
    :param inbound: what the actor knows from its messages: ``learners`` (alive), ``paused``, ``join(learners)``
    :param handle: handles one arrival ``(kind, key, payload, arrival)``
    :param status: publishes the actor's status
    """

    def __init__(self, actor: str, link: Any, inbox: Any, stream: Any, weights: Any, settings: Any, flag: Any,
                 inbound: Any, handle: Callable[[tuple], None], status: Callable[[], None]) -> None:
        self.actor, self.link, self.inbox, self.stream, self.weights = actor, link, inbox, stream, weights
        self.settings, self.flag, self.inbound, self.handle, self.status = settings, flag, inbound, handle, status
        self.waits = RateLimitStats()
        self._t_status = time.monotonic()
        self.on_hold: Callable[[], None] | None = None  # called in every period of a wait (the actor's watchdog)

    @property
    def learner_alive(self) -> bool:
        return bool(self.inbound.learners)

    def join(self) -> None:
        """Before the first step: who is alive (waiting ``learner_wait`` s for one starting up), the current weights."""
        self.inbound.join(self.link.learners_alive(timeout=1.0))
        deadline = time.monotonic() + self.settings.learner_wait
        while not self.learner_alive and not self.flag and time.monotonic() < deadline:
            self.service(block=0.1)  # a learner that appears is reported (and its task checked) by the handler
        self.query_weights(timeout=2.0)
        w = self.weights
        w.initial_version = w.version if w.version >= 0 else None

    # ------------------------------------------------------------------ inbox
    def service(self, block: float = 0.0) -> None:
        """Handle what arrived -- at most :data:`MAX_SERVICE` messages (the rest waits in Zenoh's ring buffers, which
        keep the newest, or in the bounded inbox) -- waiting up to ``block`` s for the first when nothing is waiting;
        swap weights; re-send if stalled; publish the status about once a second.

        :param block: seconds to wait for something to arrive.
        """
        first = self._arrivals(block)
        for item in first:
            self.handle(item)
        for _ in range(MAX_SERVICE - len(first)):
            item = self.inbox.get()
            if item is None:
                break
            self.handle(item)
        self.weights.swap()
        self._guard()
        self.stream.check_resend(self.learner_alive)
        now = time.monotonic()
        if now - self._t_status >= STATUS_EVERY_S:
            self._t_status = now
            self.status()

    def _guard(self) -> None:
        """What the actor's :class:`~khgrl.common.delivery.actor_guard.ActorGuard` concludes: another process as this
        actor (stop), two learners (the status says so at once), no learner of this actor's task (stop, exit 2)."""
        guard = getattr(self.inbound, "guard", None)
        if guard is None:
            return
        gate, before = self.inbound.gate, guard.alarm
        guard.learners(gate.alive_now(), gate.vouched)
        if guard.probe_due():  # an ack claimed batches never sent: the learner's next ack says whether it was forged
            newest = self.stream.outbox.newest()
            if newest is None:
                self.link.request_checkpoint()  # (acked after the checkpoint)
            else:
                self.stream.resend(newest - 1, "an ack claims batches this actor never sent: asking the learner again")
        if guard.fatal and not self.flag:
            self.flag.set("another process publishes as this actor")
        if self.inbound.wrong_task is None and (why := guard.wrong_task(bool(self.inbound.learners),
                                                                        self.settings.learner_wait)):
            self.inbound.wrong_task = why
            log.error("%s", why)
            self.flag.set("no learner of this actor's task")
        if guard.alarm != before:
            self._t_status = time.monotonic()
            self.status()

    def _arrivals(self, block: float) -> list[tuple]:
        """What waits in the link's ring buffers (at most :data:`MAX_SERVICE`), else the inbox's next item, waiting
        up to ``block`` s for either (the rings are looked at every :data:`POLL_S`)."""
        end = time.monotonic() + block
        while True:
            polled = self.link.rings.poll(MAX_SERVICE)
            if polled:
                return polled
            left = end - time.monotonic()
            item = self.inbox.get(min(POLL_S, left) if left > 0 else 0.0)
            if item is not None or left <= 0:
                return [] if item is None else [item]

    def query_weights(self, timeout: float) -> None:
        """Pull the current weights from the learner's queryable (late joiner / missed update)."""
        self.weights.last_query = time.monotonic()
        self.weights.load_replies(self.link.query_weights(timeout))

    # ------------------------------------------------------------------ flow control
    def must_wait(self) -> bool:
        """Whether the next step must wait: paused, or too far ahead of a live learner (module docstring)."""
        if self.inbound.paused:
            return True
        if not self.learner_alive or self.settings.mode == "robot":  # a robot does not wait for the learner
            return False
        s = self.stream
        trained = s.trained if s.ack_epoch is not None else s.start_index  # (a continued stream: trained before)
        return s.sent - trained >= self.settings.max_lead or self.weights.behind(s.ack_epoch, s.ack_version)

    def rate_limit(self) -> float | None:
        """Wait (servicing the inbox) while :meth:`must_wait`; the seconds waited, None if it did not wait."""
        if not self.must_wait():
            return None
        t0 = time.monotonic()
        self.waits.waits += int(not self.inbound.paused)  # flow control's waits (a hold is the safety layer's count)
        w, s = self.weights, self.stream
        while not self.flag and self.must_wait():
            if self.on_hold is not None:
                self.on_hold()
            self.service(block=0.02)
            now = time.monotonic()
            if w.behind(s.ack_epoch, s.ack_version) and now - t0 > 1.0 and now - w.last_query > 1.0:
                self.query_weights(timeout=1.0)
        dt = time.monotonic() - t0
        self.waits.wait_s += dt
        return dt

    # ------------------------------------------------------------------ the end
    def flush(self, episodes: int) -> int:
        """Wait until the learner holds every batch in a checkpoint (or ``flush_timeout``); the exit code (0, 3 when
        it timed out, 4 when another process publishes as this actor).

        :param episodes: episodes this process ran (for the log)
        """
        s = self.stream
        last = s.highest_sent
        t0 = time.monotonic()
        log.info("all %d episodes done: flushing %d batches (last seq %d)", episodes, len(s.outbox), last)
        while last >= 0 and s.durable < last and time.monotonic() - t0 < self.settings.flush_timeout \
                and not self.flag:
            self.service(block=0.05)
            if s.checkpoint_due(self.learner_alive):
                self.link.request_checkpoint()
        if getattr(getattr(self.inbound, "guard", None), "fatal", None):  # another process as this actor stopped it
            return self.split_exit()
        self.status()
        if s.durable < last:
            n = s.unconfirmed()
            log.error("flush timed out: %d transitions in %d batches not confirmed durable by the learner", n,
                      len(s.outbox))
            print(f"khgrl actor {self.actor}: flush timed out: {n} transitions not confirmed", file=sys.stderr,
                  flush=True)
            return 3
        log.info("flushed: every batch up to seq %d is in a learner checkpoint", last)
        return 0

    def split_exit(self) -> int:
        """Another process publishes as this actor id: say so (stderr, status); the exit code
        (:data:`~khgrl.common.delivery.actor_guard.SPLIT_EXIT`)."""
        from khgrl.common.delivery.actor_guard import SPLIT_EXIT

        print(f"khgrl actor {self.actor}: error: {self.inbound.guard.fatal}", file=sys.stderr, flush=True)
        self.status()
        return SPLIT_EXIT

    def finish_on_signal(self) -> int:
        """Stopped mid-episode (a signal or a stop command): publish what was collected since the last batch, then
        give the learner up to :data:`FINISH_WAIT_S` to hold every batch in a checkpoint (``khgrl up`` stops the
        actors before the learner, so its final checkpoint has them); what it does not hold stays in the outbox on
        disk, for this actor id restarted with ``--resume`` to re-send. The exit code (0)."""
        s = self.stream
        s.cut()
        last = s.highest_sent
        t0 = time.monotonic()
        while last >= 0 and s.durable < last and self.learner_alive and time.monotonic() - t0 < FINISH_WAIT_S:
            self.service(block=0.05)
            if s.checkpoint_due(self.learner_alive):
                self.link.request_checkpoint()
        log.info("stopped (%s): %d transitions not yet durable", self.flag.reason, s.unconfirmed())
        return 0
