"""The actor's watchdog: when the robot must hold still, it holds its last position sent (never a jump), the task's
``hold`` adapter hears about it every control period, and the status says why (README, "On a real robot").

The robot is held, and the control loop takes no step, while:

* the **e-stop** is pressed (``khgrl stop --now``, the e-stop key of a human-input client, the run's e-stop state
  at the start, or the supervision lost in robot mode: :mod:`khgrl.actor.supervision`): latched until the
  launcher releases it (``khgrl stop --release``); the delay from the command's timestamp to the hold is recorded
  (the sender's clock: exact on one machine, as good as the clocks' sync across machines);
* a ``pause`` holds the actor (the launcher's, or a human-input client's);
* before an episode, with ``--confirm-reset``, until a person says the robot is ready (:mod:`khgrl.actor.reset`);
* the actor waits for the learner (simulation mode: flow control, e.g. a learner that stopped training);
* a live human-input client holds the robot and has been silent for ``human_silence_s`` (a client that died
  mid-hold): until it speaks again or ``correction_timeout`` releases its hold (then the policy drives again, through
  the rate limit when it is on).

The e-stop and a pause win everywhere: also while the actor waits for a lock-step client's word (:meth:`await_word`
holds the robot until they are released, then waits on), and on the path back to the start (:mod:`khgrl.actor.reset`).

A control step that starts more than ``deadline_margin`` periods late (``--rate``) is counted: the robot held its
last position meanwhile (it is told to hold once more before the step). Every hold goes through the environment's
``hold()`` (:meth:`~khgrl.common.tasks.kgrl_env.KGRLEnv.hold`), which also restarts the rate limits at rest from the
robot's measured position: the velocity is zero after any hold, whatever its kind.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

__all__ = ["Watchdog", "EStop", "SAFETY_COUNTS", "hold_kind"]

log = logging.getLogger("khgrl.actor")

LATE_LOG_S = 10.0  # at most one log line about late steps this often
LEARNER_HOLD_S = 0.5  # a wait for the learner this long is a hold (logged, in the status); shorter: flow control
SAFETY_COUNTS = ("estops", "late_steps", "human_silence_holds", "learner_holds", "pause_holds", "ready_holds")


def hold_kind(reason: str) -> str:
    """The kind of a hold's reason: ``estop``, ``pause``, ``ready``, ``learner``, ``human`` or ``supervisor``
    (``summary.json``'s ``safety.held_s`` keys).

    :param reason: the reason the status shows.
    """
    for prefix, kind in (("e-stop", "estop"), ("paused", "pause"), ("waiting for ready", "ready"),
                         ("waiting for the learner", "learner"), ("human client", "human"),
                         ("waiting for the supervisor", "supervisor")):
        if reason.startswith(prefix):
            return kind
    return "other"


@dataclass
class EStop:
    """One press of the e-stop.

    :param by: who pressed it ("launcher" or "human client <id>").
    :param sent: the command's timestamp (the sender's ``time.time()``).
    :param episode: the episode the actor was in.
    :param t: the step it was about to take.
    """

    by: str
    sent: float
    episode: int
    t: int
    latency_ms: float | None = None  # from the command's timestamp to the actor's first held period
    also: list = field(default_factory=list)  # who pressed it again while it held (named in the held reason)


@dataclass
class _Holding:
    reason: str
    since: float  # monotonic


@dataclass
class Watchdog:
    """Holds the robot and says why (module docstring).

    :param env: the actor's :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` (``hold()``, ``t``).
    :param inbound: the actor's :class:`~khgrl.actor.inbound.Inbound` (``held_reason``, ``estop``).
    :param arbiter: the :class:`~khgrl.actor.arbiter.CorrectionArbiter` (``silent``, ``holder``, ``deadline``).
    :param human_silence_s: a silent holder's limit (0: off).
    :param deadline_margin: late steps, in periods (0: off).
    :param period: the control period (s; 0: free-running, no deadlines).
    :param service: the loop's inbox service (``service(block=seconds)``), called while it holds.
    :param wait: the loop's wait while it is held (the e-stop, a pause): returns when released or stopped.
    :param status: publishes the actor's status (at once when a hold starts or ends).
    :param stopped: whether the actor is to stop.
    """

    env: Any
    inbound: Any
    arbiter: Any
    human_silence_s: float = 0.3
    deadline_margin: float = 1.0
    period: float = 0.0
    service: Callable[..., None] = lambda block=0.0: None
    wait: Callable[[], None] = lambda: None
    status: Callable[[], None] = lambda: None
    stopped: Callable[[], bool] = lambda: False
    counts: dict = field(default_factory=lambda: dict.fromkeys(SAFETY_COUNTS, 0))
    held_s: dict = field(default_factory=dict)  # reason kind -> seconds held
    estops: list = field(default_factory=list)
    paths: list = field(default_factory=list)  # the reset paths between episodes (actor/reset.py)
    late_ms_max: float = 0.0
    _now: _Holding | None = None
    _waiting_since: float | None = None  # when the current wait began
    _late_logged: float = -float("inf")

    @property
    def reason(self) -> str:
        """Why the robot is held now ("" when it is not)."""
        return self._now.reason if self._now is not None else ""

    def holding(self) -> None:
        """The loop waits (paused, e-stopped or for the learner): hold the robot, note why (called about every
        20 ms while it waits; a wait for the learner becomes a hold after :data:`LEARNER_HOLD_S`)."""
        now = time.monotonic()
        if self._waiting_since is None:
            self._waiting_since = now
        why = self.inbound.held_reason
        if not why and now - self._waiting_since < LEARNER_HOLD_S:  # flow control, every few steps in simulation
            self.env.hold()
            return
        self._enter(why or "waiting for the learner")
        stop = self.inbound.estop
        if stop is not None and stop.latency_ms is None:
            stop.latency_ms = (time.time() - stop.sent) * 1e3
            log.warning("e-stop by %s: robot held at episode %d step %d, %.1f ms after the command", stop.by,
                        stop.episode, stop.t, stop.latency_ms)
            self.estops.append(stop)
            self.counts["estops"] += 1
        self.env.hold()

    def released(self) -> None:
        """The wait is over: the loop steps again."""
        self._waiting_since = None
        if self._now is None:
            return
        kind = hold_kind(self._now.reason)
        self.held_s[kind] = self.held_s.get(kind, 0.0) + time.monotonic() - self._now.since
        log.info("robot released (%s for %.2f s)", self._now.reason, time.monotonic() - self._now.since)
        self._now = None
        self.status()

    def _enter(self, reason: str) -> None:
        if self._now is not None and self._now.reason == reason:
            return
        if self._now is not None:
            self.released()
        self._now = _Holding(reason, time.monotonic())
        key = {"pause": "pause_holds", "learner": "learner_holds", "ready": "ready_holds"}.get(hold_kind(reason))
        if key is not None:
            self.counts[key] += 1
        log.info("robot held: %s", reason)
        self.status()

    def human_silence(self) -> bool:
        """Hold while a live client holding the robot is silent longer than ``human_silence_s``: until it speaks
        again, or its silence reaches ``correction_timeout`` (the arbiter then releases it at the next step), or a
        command holds the actor; returns whether it held.
        """
        arb = self.arbiter
        if self.human_silence_s <= 0 or arb.silent(time.monotonic()) <= self.human_silence_s:
            return False
        client = arb.holder
        self.counts["human_silence_holds"] += 1
        self._enter(f"human client {client} silent for more than {self.human_silence_s:g} s")
        while not self.stopped() and arb.holder == client and arb.silent(time.monotonic()) > self.human_silence_s \
                and time.monotonic() <= arb.deadline and not self.inbound.paused:
            self.service(block=0.02)
            self.env.hold()
        self.released()
        return True

    def await_word(self, step: int) -> None:
        """A lock-step correction client has not yet sent its word for ``step``: the robot holds while the actor
        waits for it (servicing the inbox), at most the correction timeout; then it carries on without it. The
        e-stop or a pause that comes meanwhile wins: the robot is held (:attr:`wait`) until released, and the wait
        for the word goes on after it (the time held does not count).

        :param step: the step about to be taken.
        """
        t0 = time.monotonic()
        arb = self.arbiter
        arb.counts["lockstep_waits"] += 1
        while not self.stopped():
            if self.inbound.paused:  # (checked before the word: both may come in one service)
                held = time.monotonic()
                self.wait()
                t0 += time.monotonic() - held
                continue
            if arb.ready(step):
                break
            if time.monotonic() - t0 > arb.timeout:
                arb.give_up(step)
                break
            self.service(block=0.002)

    def late(self, lateness: float) -> None:
        """The step starts ``lateness`` s after its deadline: count it when beyond the margin.

        :param lateness: seconds late (<= 0: on time).
        """
        if self.period <= 0 or self.deadline_margin <= 0 or lateness <= self.deadline_margin * self.period:
            return
        self.counts["late_steps"] += 1
        self.env.hold()  # the robot stood still meanwhile: the next step starts at rest from where it is
        self.late_ms_max = max(self.late_ms_max, lateness * 1e3)
        now = time.monotonic()
        if now - self._late_logged >= LATE_LOG_S:  # (at most one line per LATE_LOG_S: a loaded machine is late often)
            self._late_logged = now
            log.warning("control step %.1f ms late (the robot held its last position meanwhile; %d late steps so far)",
                        lateness * 1e3, self.counts["late_steps"])

    def summary(self) -> dict:
        """What ``summary.json`` says under ``safety``."""
        return {**self.counts, "held_s": {k: round(v, 3) for k, v in self.held_s.items()},
                "late_ms_max": round(self.late_ms_max, 2),
                "estop_latency_ms": [None if e.latency_ms is None else round(e.latency_ms, 2) for e in self.estops],
                "estop_events": [{"by": e.by, "episode": e.episode, "t": e.t, "latency_ms": e.latency_ms}
                                 for e in self.estops], "reset_paths": self.paths}
