"""Which human correction drives the actor at each step: one client at a time, live or in lock-step, with
timeouts (docs/protocol.md, "Corrections").

Nothing here touches Zenoh or the environment: the control loop offers it every validated
:class:`~khgrl.common.wire.messages.Correction` and asks it, before each step, whether it may step (:meth:`ready`) and
which P_h applies (:meth:`current`).
"""

from __future__ import annotations

import logging

import numpy as np
from khgrl.actor.human_limits import MAX_CLIENTS, Assignments, HoldAllowance, far_outside
from khgrl.common.wire.messages import Correction

__all__ = ["CorrectionArbiter"]

log = logging.getLogger("khgrl.actor")

COUNTS = ("applied", "ignored_other_client", "ignored_other_actor", "ignored_method", "stale_episode", "timeouts",
          "releases", "episode_end_releases", "holds", "projected_steps", "addressed", "late_step", "lockstep_waits",
          "lockstep_timeouts", "lockstep_skipped", "holds_expired", "holds_refused", "not_assigned", "far_outside")


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
    plain mode (:meth:`give_up`), at once if its word for a later step came first (it skipped this one); after
    that it is not waited for again in this episode, and in as many following episodes as it has been given up on
    before (1, 2, 4, ... : a client that keeps skipping costs the actor one give-up in ever longer stretches).

    A client's power is bounded (:mod:`khgrl.actor.human_limits`): it must be assigned to this actor
    (``assignments``), its P_h may lie at most :data:`~khgrl.actor.human_limits.FAR_MARGIN` of the workspace's
    extent outside the workspace (``workspace``; farther is refused, not projected), and its holds spend an
    allowance of running time (``allowance``). :meth:`offer` returns why a correction was refused (the caller counts
    it as a rejected message).

    :param actor: this actor's id (corrections for other actors are counted and ignored).
    :param timeout: seconds of silence after which a holder loses the robot.
    :param enabled: False for KGRL: every correction is counted and ignored.
    :param workspace: ``(low, high)`` of the task's workspace (None: P_h is not checked here).
    :param allowance: each client's holding allowance (None: unlimited).
    :param assignments: which clients may drive this actor (None: every client).
    """

    MAX_AHEAD = 64  # step-addressed messages kept ahead of the current step

    def __init__(self, actor: str, timeout: float, enabled: bool, *, workspace: tuple | None = None,
                 allowance: HoldAllowance | None = None, assignments: Assignments | None = None) -> None:
        self.actor = actor
        self.timeout = float(timeout)
        self.enabled = enabled
        self.workspace = None if workspace is None else tuple(np.asarray(w, np.float64) for w in workspace)
        self.allowance = allowance or HoldAllowance(0.0, 0.0)
        self.assignments = assignments or Assignments(actor)
        self.episode = 0
        self._waited = 0.0  # seconds the actor waited (paused, flow control): not running time
        self._last_tick: float | None = None  # running time of the last step (for the allowance)
        self._strikes: dict[str, int] = {}  # lock-step client -> times it was given up on
        self._not_waited: dict[str, int] = {}  # lock-step client -> last episode it is not waited for
        self.holder: str | None = None
        self.p_h: np.ndarray | None = None
        self.word: Correction | None = None  # the correction that set p_h (its signature vouches for the rows)
        self.deadline = 0.0
        self.heard = 0.0  # when the holder was last heard from (time.monotonic(), shifted by the actor's waits)
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
        self.episode = episode
        if self._announced is not None and self._announced[0] == episode:
            msg = self._announced[1]
            if self._waits_for(msg.client):
                self.lockstep, self._addressed[0] = msg.client, msg
        self._announced = None

    def _waits_for(self, client: str) -> bool:
        """Whether ``client`` may put the actor in lock-step in this episode (not given up on lately)."""
        return self._not_waited.get(client, -1) < self.episode

    def offer(self, msg: Correction, arrival: float, episode: int, step: int = 0) -> str | None:
        """Take a validated correction into account; returns why it was refused (None: taken or ignored).

        :param msg: the correction (its ``client`` already checked against the key it came on).
        :param arrival: when it arrived (``time.monotonic()``).
        :param episode: the episode the actor is in.
        :param step: the step the actor is about to take.
        """
        self.episode = episode
        if msg.actor != self.actor:
            self.counts["ignored_other_actor"] += 1
            return None
        if not self.enabled:
            self.counts["ignored_method"] += 1
            return None
        if why := self._refusal(msg):
            return why
        if self.holder is not None and msg.client != self.holder:
            self.counts["ignored_other_client"] += 1
            return None
        if msg.step is not None and (self._waits_for(msg.client) or msg.episode != episode):
            self._offer_addressed(msg, episode, step)
            return None
        if not msg.active:
            if self.holder == msg.client:
                self._release()
            return None
        if msg.episode is not None and msg.episode != episode:
            self.counts["stale_episode"] += 1
            return None
        self._hold(msg, arrival)
        return None

    def _refusal(self, msg: Correction) -> str | None:
        """Why ``msg`` is refused outright: a client not assigned to this actor, or a P_h far outside the
        workspace."""
        if not self.assignments.allows(msg.client):
            self.counts["not_assigned"] += 1
            return f"client {msg.client!r} is not assigned to actor {self.actor} (human_clients)"
        if msg.active and self.workspace is not None and (why := far_outside(msg.p_h, *self.workspace)):
            self.counts["far_outside"] += 1
            return why
        return None

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
        """Whether the actor may take ``step``: True unless a lock-step client has not yet sent its word for it. A
        client whose word for a later step came first skipped this one (its words arrive in order): it is given up
        on at once (counted ``lockstep_skipped``).

        :param step: the step about to be taken.
        """
        if self.lockstep is None or step in self._addressed:
            return True
        if any(s > step for s in self._addressed):
            self.counts["lockstep_skipped"] += 1
            self.give_up(step, "skipped it (its word for a later step came first)")
            return True
        return False

    def give_up(self, step: int, why: str = "sent nothing for it in time") -> None:
        """The lock-step client said nothing for ``step`` in time: carry on in plain mode (latest wins), and do not
        wait for that client again in this episode nor, after its n-th give-up, in the 2**(n-1) - 1 episodes after.

        :param step: the step it was silent at.
        :param why: what it did (for the log).
        """
        client = self.lockstep
        if client is not None:
            strikes = self._strikes.pop(client, 0) + 1
            if len(self._strikes) >= MAX_CLIENTS:
                self._strikes.pop(next(iter(self._strikes)))
                self._not_waited.pop(next(iter(self._not_waited)), None)
            self._strikes[client] = strikes
            self._not_waited[client] = self.episode + 2 ** (strikes - 1) - 1
        log.warning("lock-step correction client %s %s at step %d: not waiting for it again before episode %d",
                    client, why, step, self._not_waited.get(client, self.episode) + 1)
        self.counts["lockstep_timeouts"] += 1
        self.lockstep = None
        self._addressed.clear()

    def _hold(self, msg: Correction, arrival: float) -> None:
        client = msg.client
        if self.holder is None:
            if not self.allowance.may_start(client, arrival - self._waited):
                self.counts["holds_refused"] += 1
                return
            self.holder = client
            self.counts["holds"] += 1
        self.p_h, self.word = np.asarray(msg.p_h, dtype=np.float64), msg
        self.deadline, self.heard = arrival + self.timeout, arrival
        self.counts["applied"] += 1

    def _release(self) -> None:
        self.holder, self.p_h, self.word = None, None, None
        self.counts["releases"] += 1

    def extend(self, seconds: float) -> None:
        """The actor paused for ``seconds``: the holder's silence during it does not count.

        :param seconds: how long the actor waited.
        """
        self._waited += seconds
        if self.holder is not None:
            self.deadline += seconds
            self.heard += seconds

    def silent(self, now: float) -> float:
        """Seconds a live (not lock-step) holder has been silent (0.0 when nobody holds, or in lock-step, where the
        actor waits for each word anyway): the watchdog's measure (:mod:`khgrl.actor.safety`).

        :param now: ``time.monotonic()``.
        """
        if self.holder is None or self.lockstep is not None:
            return 0.0
        return max(0.0, now - self.heard)

    def _charge(self, now: float) -> None:
        """The holder held since the last step: spend its allowance; release it when that runs out."""
        run = now - self._waited
        last, self._last_tick = self._last_tick, run
        if self.holder is None or last is None or self.allowance.unlimited:
            return
        if self.allowance.spend(self.holder, max(0.0, run - last), run) <= 0.0:
            log.warning("correction client %s held actor %s for its whole allowance (%.0f s of running time): "
                        "released", self.holder, self.actor, self.allowance.capacity)
            self.counts["holds_expired"] += 1
            self._release()

    def current(self, now: float, step: int | None = None) -> np.ndarray | None:
        """P_h to apply at ``step`` (None: no intervention). In lock-step, the client's word for that step.

        :param now: ``time.monotonic()`` (for the silence timeout).
        :param step: the step about to be taken (None: plain mode only).
        """
        self._charge(now)
        if self.lockstep is not None and step is not None:
            msg = self._addressed.pop(step, None)
            for s in [s for s in self._addressed if s < step]:
                del self._addressed[s]
            if msg is not None:
                if msg.active:
                    self._hold(msg, now)
                elif self.holder == msg.client:
                    self._release()
                return self.p_h
        if self.holder is not None and now > self.deadline:
            log.info("correction client %s silent for > %.2f s: intervention ended", self.holder, self.timeout)
            self.holder, self.p_h, self.word = None, None, None
            self.counts["timeouts"] += 1
        return self.p_h
