"""What an actor concludes from its acks and the learners alive that no single message proves (docs/protocol.md,
"Split brain"): another process publishes as this actor id, two learners run for one run, or a learner is of
another task. Pure logic, no Zenoh: :class:`~khgrl.actor.inbound.Inbound` and
:class:`~khgrl.common.delivery.actor_side.ActorDelivery` feed it.

* **Another process publishes as this actor** (:attr:`ActorGuard.fatal`; the actor stops, exit
  :data:`SPLIT_EXIT`): :data:`BEYOND_ACKS` acks in a row, over at least :data:`BEYOND_SPAN_S`, from a live learner
  epoch, each claiming a batch of this stream that this process never sent (someone else published it with this
  stream id: the learner holds it, so every later ack claims it; one forged ack is not enough). After such an ack
  the actor asks the learner again every :data:`BEYOND_PROBE_S` (:meth:`ActorGuard.probe_due`: it re-sends its
  newest batch, which the learner acks): a frozen actor gets no acks otherwise, and a forged ack is answered by a
  genuine one that breaks the run. Or acks of
  this actor id for *another* stream whose ``received`` moves forward :data:`OTHER_ADVANCES` times (someone else
  publishes a stream of this id), or the learner's ``superseded`` ack for this stream (signed, or -- without the
  key -- after an ack of another stream of this id). With the run's key only authentic acks count.
* **Two learners** (:attr:`ActorGuard.alarm`, in the actor's status; ``khgrl up`` ends the run): two learner epochs
  alive at once for :data:`TWO_LEARNERS_S` -- with the run's key, only epochs that signed an ack or weights this
  actor took (a token alone, which anyone can declare in plain mode, is not enough). A restarted learner waits for
  its predecessor's token to go before declaring its own, so a restart never looks like two.
* **A learner of another task** is ignored (counted, logged, not followed); the actor stops (exit 2) only when no
  learner of its own task is alive ``learner_wait`` s after such a learner was seen.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

from khgrl.common.delivery import data_keys

__all__ = ["ActorGuard", "SPLIT_EXIT", "BEYOND_ACKS", "BEYOND_SPAN_S", "BEYOND_PROBE_S", "OTHER_ADVANCES",
           "TWO_LEARNERS_S"]

log = logging.getLogger("khgrl.actor")

SPLIT_EXIT = 4  # the actor's exit code when another process publishes as it
BEYOND_ACKS = 3  # acks in a row claiming batches never sent ...
BEYOND_SPAN_S = 0.5  # ... over at least this long
BEYOND_PROBE_S = 0.5  # after such an ack: ask the learner again this often ...
BEYOND_PROBE_FOR_S = 3.0  # ... while the last one is at most this old
OTHER_ADVANCES = 2  # times the acks of another stream of this actor id moved forward
TWO_LEARNERS_S = 2.0  # two learner epochs alive this long: two learners in one run
MAX_OTHER_STREAMS = 16  # other stream ids followed at most


class ActorGuard:
    """Watches one actor's acks and the learners alive (see the module docstring).

    :param actor: this actor's id.
    :param stream: this process's stream id.
    :param key: the run's key (None: acks are not authenticated).
    :param clock: monotonic seconds.
    """

    def __init__(self, actor: str, stream: str, key: data_keys.Keyish = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.actor, self.stream, self.key, self.clock = actor, stream, key, clock
        self.fatal: str | None = None  # another process publishes as this actor: why, in one line
        self.alarm: str | None = None  # the line for the status (fatal, or two learners)
        self._beyond: list[float] = []  # when each ack of the current run of "beyond" acks came
        self._probed = -1e9
        self._others: dict[str, list[int]] = {}  # other stream id -> [highest received, advances]
        self._two_since: float | None = None
        self.wrong: dict[str, str] = {}  # learner liveliness key ignored -> why (another task)
        self.wrong_since: float | None = None  # when a learner of another task was seen with none of ours alive

    # ------------------------------------------------------------------ acks
    def authentic(self, ack: Any) -> str | None:
        """Why ``ack`` is not authentic (None: it is, or there is no key).

        :param ack: a decoded ack.
        """
        return data_keys.check(ack, self.key)

    def on_ack(self, ack: Any, max_published: int, live_epochs: set) -> None:
        """An ack for this actor id arrived (before the stream takes or refuses it).

        :param ack: the decoded ack.
        :param max_published: the highest seq this process (and its stream's earlier processes) published.
        :param live_epochs: the epochs of the learner tokens alive now.
        """
        if ack.actor != self.actor or ack.epoch not in live_epochs or ack.superseded or self.authentic(ack):
            return
        if ack.stream == self.stream:
            if ack.received > max_published or ack.durable > max_published:
                self._beyond.append(self.clock())
                if len(self._beyond) >= BEYOND_ACKS and self._beyond[-1] - self._beyond[0] >= BEYOND_SPAN_S:
                    self._stop(f"with this process's stream id {self.stream}: the learner holds batches of it up to "
                               f"seq {max(ack.received, ack.durable)}, but this process sent only up to seq "
                               f"{max_published} ({len(self._beyond)} acks in a row over "
                               f"{self._beyond[-1] - self._beyond[0]:.1f} s)")
            return
        if ack.stream is None:
            return
        seen = self._others.get(ack.stream)
        if seen is None:
            if len(self._others) < MAX_OTHER_STREAMS:
                self._others[ack.stream] = [ack.received, 0]
            return
        if ack.received > seen[0]:
            seen[0], seen[1] = ack.received, seen[1] + 1
            if seen[1] >= OTHER_ADVANCES:
                self._stop(f"with another stream id {ack.stream} (this process: stream {self.stream}): the learner "
                           f"took its batches up to seq {ack.received}")

    def probe_due(self) -> bool:
        """Whether to ask the learner for a new ack now: an ack claimed batches never sent, lately, and no ack was
        taken since (the caller re-sends its newest batch)."""
        now = self.clock()
        if self.fatal or not self._beyond or now - self._beyond[-1] > BEYOND_PROBE_FOR_S \
                or now - self._probed < BEYOND_PROBE_S:
            return False
        self._probed = now
        return True

    def corroborated(self) -> bool:
        """Whether an ack of another stream of this actor id came from a live learner (what makes an unauthenticated
        ``superseded`` believable)."""
        return bool(self._others)

    def accepted(self) -> None:
        """An ack for this stream was taken: a run of "beyond" acks is broken."""
        self._beyond.clear()

    def superseded(self) -> None:
        """The learner said (authenticated, or corroborated: :meth:`corroborated`) that it took another stream of this
        actor id after this one: the same conclusion as the acks'."""
        self._stop(f"(the learner took another stream of this id after this one, stream {self.stream}, and refuses "
                   f"it)")

    def _stop(self, evidence: str) -> None:
        if self.fatal is None:
            self.fatal = self.alarm = f"another process publishes as actor {self.actor} {evidence}: this one stops"
            log.error("%s", self.fatal)

    # ------------------------------------------------------------------ learners
    def learners(self, alive: dict, vouched: set) -> None:
        """The learner tokens alive now (called between steps): raises :attr:`alarm` after :data:`TWO_LEARNERS_S`
        of two epochs.

        :param alive: liveliness key -> epoch, of the learners followed.
        :param vouched: the epochs that signed a message this actor took (used with the run's key only).
        """
        epochs = {e: k for k, e in alive.items() if self.key is None or e in vouched}
        if len(epochs) < 2:
            self._two_since = None
            return
        now = self.clock()
        if self._two_since is None:
            self._two_since = now
        elif now - self._two_since >= TWO_LEARNERS_S and self.alarm is None:
            self.alarm = (f"two learners run for this run: {', '.join(sorted(epochs.values()))} alive together for "
                          f"{now - self._two_since:.1f} s (one learner per run: another process runs as a learner)")
            log.error("%s", self.alarm)

    def ignore(self, key: str, why: str, ours_alive: bool) -> None:
        """A learner of another task: ignored from now on.

        :param key: its liveliness key.
        :param why: the two tasks, in words.
        :param ours_alive: whether a learner of this actor's task is alive.
        """
        if key not in self.wrong:
            log.error("ignoring learner %s: %s", key, why)
        self.wrong[key] = why
        if not ours_alive and self.wrong_since is None:
            self.wrong_since = self.clock()

    def wrong_task(self, ours_alive: bool, wait_s: float) -> str | None:
        """Why the actor must stop (exit 2): a learner of another task seen ``wait_s`` s ago and none of this actor's
        task alive since (None: carry on).

        :param ours_alive: whether a learner of this actor's task is alive.
        :param wait_s: the actor's ``learner_wait``.
        """
        if ours_alive:
            self.wrong_since = None
            return None
        if self.wrong_since is None or self.clock() - self.wrong_since < wait_s:
            return None
        return next(iter(self.wrong.values())) + f" (and no learner of this actor's task came within {wait_s:g} s)"
