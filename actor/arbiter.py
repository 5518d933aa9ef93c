"""Which human correction drives the actor at each step: one client at a time, live or in lock-step, with
timeouts (docs/protocol.md, "Corrections").

Nothing here touches Zenoh or the environment: the control loop offers it every validated
:class:`~khgrl.common.wire.messages.Correction` and asks it, before each step, whether it may step (:meth:`ready`) and
which P_h applies (:meth:`current`).
"""

from __future__ import annotations

import logging

import numpy as np
from khgrl.common.wire.messages import Correction

__all__ = ["CorrectionArbiter"]

log = logging.getLogger("khgrl.actor")

COUNTS = ("applied", "ignored_other_client", "ignored_other_actor", "ignored_method", "stale_episode", "timeouts",
          "releases", "episode_end_releases", "holds", "projected_steps", "addressed", "late_step", "lockstep_waits",
          "lockstep_timeouts")


class CorrectionArbiter:
    """One human-input client drives the actor at a time: the first client that sends an active correction
    holds the intervention until it sends ``active=False``, is silent longer than ``timeout`` (of the
    actor's running time: pauses of the actor, e.g. waiting for the learner, extend the deadline, since the
    client gets no frames then), or the episode ends (a hold never carries into the next episode).

    Corrections come in two kinds (docs/protocol.md). A live client (a person at the GUI) sends plain ones:
    the latest wins and applies to the actor's next step. A step-addressed one names the step it is for
    (``step``, with ``episode``): a client that sends one is *in lock-step* for the rest of that episode --
    the actor does not take a step before it has that client's word (P_h or release) for it (:meth:`ready`),
    so a scripted or replayed correction applies exactly at the step it was computed for, whatever the
    latency. A word for step 0 of the *next* episode, sent while this one runs, announces lock-step from that
    episode's first step. A lock-step client that stays silent for ``timeout`` at a step is dropped back to
    plain mode (:meth:`give_up`).

    :param actor: this actor's id (corrections for other actors are counted and ignored).
    :param timeout: seconds of silence after which a holder loses the robot.
    :param enabled: False for KGRL: every correction is counted and ignored.
    """

    MAX_AHEAD = 64  # step-addressed messages kept ahead of the current step

    def __init__(self, actor: str, timeout: float, enabled: bool) -> None:
        self.actor = actor
        self.timeout = float(timeout)
        self.enabled = enabled
        self.holder: str | None = None
        self.p_h: np.ndarray | None = None
        self.deadline = 0.0
        self.lockstep: str | None = None  # client whose step-addressed word each step of this episode waits for
        self._addressed: dict[int, Correction] = {}  # step -> that client's message for it
        self._announced: tuple[int, Correction] | None = None  # (next episode, a client's word for its step 0)
        self.counts: dict[str, int] = dict.fromkeys(COUNTS, 0)

    def new_episode(self, episode: int) -> None:
        """Start ``episode``: any hold ends with the episode before it (a live one too: its P_h was for that
        episode's robot), and lock-step lasts one episode -- a client re-enters it with a word for the new
        episode (announced during the last one, or its first step-addressed message).

        :param episode: the episode about to start (1-based, whole run).
        """
        if self.holder is not None:
            self._release()
            self.counts["episode_end_releases"] += 1
        self.lockstep = None
        self._addressed.clear()
        if self._announced is not None and self._announced[0] == episode:
            msg = self._announced[1]
            self.lockstep, self._addressed[0] = msg.client, msg
        self._announced = None

    def offer(self, msg: Correction, arrival: float, episode: int, step: int = 0) -> None:
        """Take a validated correction into account.

        :param msg: the correction (its ``client`` already checked against the key it came on).
        :param arrival: when it arrived (``time.monotonic()``).
        :param episode: the episode the actor is in.
        :param step: the step the actor is about to take.
        """
        if msg.actor != self.actor:
            self.counts["ignored_other_actor"] += 1
            return
        if not self.enabled:
            self.counts["ignored_method"] += 1
            return
        if self.holder is not None and msg.client != self.holder:
            self.counts["ignored_other_client"] += 1
            return
        if msg.step is not None:
            self._offer_addressed(msg, episode, step)
            return
        if not msg.active:
            if self.holder == msg.client:
                self._release()
            return
        if msg.episode is not None and msg.episode != episode:
            self.counts["stale_episode"] += 1
            return
        self._hold(msg.client, msg.p_h, arrival)

    def _offer_addressed(self, msg: Correction, episode: int, step: int) -> None:
        if msg.episode == episode + 1 and msg.step == 0:  # announces lock-step for the next episode
            self._announced = (episode + 1, msg)
            self.counts["addressed"] += 1
            return
        if msg.episode != episode:
            self.counts["stale_episode"] += 1
            return
        if self.lockstep is not None and msg.client != self.lockstep:
            self.counts["ignored_other_client"] += 1
            return
        if msg.step < step:
            self.counts["late_step"] += 1  # the step it was meant for is already taken
            return
        self.lockstep = msg.client
        self.counts["addressed"] += 1
        if len(self._addressed) < self.MAX_AHEAD or msg.step in self._addressed:
            self._addressed[msg.step] = msg

    def ready(self, step: int) -> bool:
        """Whether the actor may take ``step``: True unless a lock-step client has not yet sent its word for it.

        :param step: the step about to be taken.
        """
        return self.lockstep is None or step in self._addressed

    def give_up(self, step: int) -> None:
        """The lock-step client said nothing for ``step`` in time: carry on in plain mode (latest wins).

        :param step: the step it was silent at.
        """
        log.warning("lock-step correction client %s sent nothing for step %d: no longer waiting for it this episode",
                    self.lockstep, step)
        self.counts["lockstep_timeouts"] += 1
        self.lockstep = None
        self._addressed.clear()

    def _hold(self, client: str, p_h, arrival: float) -> None:
        if self.holder is None:
            self.holder = client
            self.counts["holds"] += 1
        self.p_h = np.asarray(p_h, dtype=np.float64)
        self.deadline = arrival + self.timeout
        self.counts["applied"] += 1

    def _release(self) -> None:
        self.holder, self.p_h = None, None
        self.counts["releases"] += 1

    def extend(self, seconds: float) -> None:
        """The actor paused for ``seconds``: the holder's silence during it does not count.

        :param seconds: how long the actor waited.
        """
        if self.holder is not None:
            self.deadline += seconds

    def current(self, now: float, step: int | None = None) -> np.ndarray | None:
        """P_h to apply at ``step`` (None: no intervention). In lock-step, the client's word for that step.

        :param now: ``time.monotonic()`` (for the silence timeout).
        :param step: the step about to be taken (None: plain mode only).
        """
        if self.lockstep is not None and step is not None:
            msg = self._addressed.pop(step, None)
            for s in [s for s in self._addressed if s < step]:
                del self._addressed[s]
            if msg is not None:
                if msg.active:
                    self._hold(msg.client, msg.p_h, now)
                elif self.holder == msg.client:
                    self._release()
                return self.p_h
        if self.holder is not None and now > self.deadline:
            log.info("correction client %s silent for > %.2f s: intervention ended", self.holder, self.timeout)
            self.holder, self.p_h = None, None
            self.counts["timeouts"] += 1
        return self.p_h
