"""What the actor does with what arrives between steps: acks, corrections, control commands and learner
liveliness. The control loop (:mod:`khgrl.actor.loop`) takes them out of its inbox and hands them to :class:`Inbound`.

Here too are the actor's checks that hold without access control (docs/protocol.md): the
:class:`~khgrl.common.delivery.trust.WeightsGate` is installed in the weights receiver and told which learner epochs
are alive
(weights only from those, with plausible versions); an ack whose weights version is implausible is refused like
one that claims batches never sent, and with the run's key (:mod:`~khgrl.common.delivery.run_key`) so is one
without the learner's ``mac``; a ``superseded`` ack is obeyed only when authenticated (without the key: once an
ack of another stream of this id came; that stream's acks also stop the actor:
:class:`~khgrl.common.delivery.actor_guard.ActorGuard`);
a learner of another task is ignored (the actor stops only if none of its own task comes). With the run's role keys
(``RUN_DIR/keys``) control is taken only signed by the operator (a human-input client's request by that client's
key), fresh and not replayed (:class:`~khgrl.common.delivery.control_auth.ControlGate`): anything else is counted and
logged as a rejected message. Without them a ``stop`` or ``pause`` that does not come from the launcher is obeyed but
logged as such (a warning with its sender and key). Any human-input client may press the e-stop; its ``pause`` holds
only the actors it is assigned to and ends unless renewed within
``human_pause_s`` (:class:`~khgrl.actor.human_limits.HumanPauses`); a correction the arbiter refuses (a client not
assigned to this actor, P_h far outside the workspace) is counted and logged as a rejected message.

One module of ~330 lines on purpose: one class, the actor's handling of every inbound message kind between steps.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from khgrl.actor.human_limits import HumanPauses
from khgrl.actor.safety import EStop
from khgrl.actor.supervision import Supervision, heartbeat_refusal
from khgrl.common.delivery.actor_guard import ActorGuard
from khgrl.common.delivery.estop_state import STATE_FILE, read_state
from khgrl.common.delivery.senders import HUMAN_COMMANDS, read_for_actor
from khgrl.common.delivery.trust import WeightsGate, learner_of
from khgrl.common.process import StopFlag
from khgrl.common.wire.checks import ProtocolError
from khgrl.common.wire.control import HEARTBEAT_ESTOP, HEARTBEATS
from khgrl.common.wire.messages import Ack, Control, Dims
from khgrl.common.wire.protocol import attribute_control

__all__ = ["Inbound", "HUMAN_COMMANDS", "MAX_LEARNERS", "NEW_LEARNERS_PER_S"]

log = logging.getLogger("khgrl.actor")

# Learner liveliness tokens: each new one costs a task query and a re-send of the outbox, so an actor follows at most
# MAX_LEARNERS at once and takes at most NEW_LEARNERS_PER_S new ones a second (bursts of MAX_LEARNERS); the rest are
# refused (counted in rejects.alive, logged at a bounded rate). A run has one learner; a restarted one is one more.
MAX_LEARNERS = 4
NEW_LEARNERS_PER_S = 1.0


class Inbound:
    """Handles the actor's incoming messages and keeps what they tell: the learners alive, paused, and why the
    actor must stop with exit code 2 (no learner of its task) or 4 (its ``guard``: another process as its id).

    :param parts: the loop's :class:`~khgrl.actor.parts.ActorParts`.
    :param flag: the process's stop flag.
    :param dims: the sizes corrections must have.
    :param gate: the weights gate (default: a new one), installed in ``parts.weights.receiver``.
    :param guard: the actor's :class:`~khgrl.common.delivery.actor_guard.ActorGuard` (default: one with the gate's
        key, the run's).
    :param pause_s: seconds a human-input client's pause lasts unless renewed (0: until resumed).
    :param supervision: the supervisor's heartbeats (:mod:`khgrl.actor.supervision`; default: not required).
    """

    def __init__(self, parts: Any, flag: StopFlag, dims: Dims, gate: WeightsGate | None = None,
                 guard: ActorGuard | None = None, pause_s: float = 60.0,
                 supervision: Supervision | None = None) -> None:
        self.p, self.flag, self.dims = parts, flag, dims
        self.supervision = supervision or Supervision(False, 1.0)
        self.learners: set[str] = set()
        self.launcher_paused = False  # control/actor or control/all pause (the launcher's: no expiry)
        self.estop: EStop | None = None  # the e-stop, pressed (latched until the launcher's release)
        self.episode = 0  # the actor's episode (as of the last message handled)
        self.awaiting_ready: int | None = None  # the episode that waits for a person's ready (--confirm-reset)
        self.human_pauses = HumanPauses(pause_s)
        self._new_learners = (float(MAX_LEARNERS), time.monotonic())  # token bucket: (tokens, when)
        self.wrong_task: str | None = None
        self.guard = guard or ActorGuard(parts.stream.actor, parts.stream.stream, getattr(gate, "key", None))
        self.gate = gate or WeightsGate(key=self.guard.key)
        parts.weights.receiver.use_gate(self.gate)

    def join(self, learners: set[str]) -> None:
        """The learners found alive before the first step (a liveliness query).

        :param learners: their liveliness keys.
        """
        taken = [key for key in sorted(learners) if self._admit_learner(key)]
        for key in taken:
            self.learners.add(key)
            self.p.weights.receiver.learner_appeared(key)
        if taken:
            self.check_learner_task()

    def _admit_learner(self, key: str) -> bool:
        """Whether a learner token not followed yet is taken (see :data:`MAX_LEARNERS`); a refused one is counted."""
        tokens, since = self._new_learners
        now = time.monotonic()
        tokens = min(float(MAX_LEARNERS), tokens + NEW_LEARNERS_PER_S * (now - since))
        if len(self.learners) >= MAX_LEARNERS or tokens < 1.0:
            self._new_learners = (tokens, now)
            self.p.rejects.reject("alive", key, ProtocolError(
                f"learner token refused: {len(self.learners)} learners followed (at most {MAX_LEARNERS}, and at most "
                f"{NEW_LEARNERS_PER_S:g} new a second)"))
            return False
        self._new_learners = (tokens - 1.0, now)
        return True

    @property
    def paused(self) -> bool:
        """Whether the actor is held: the e-stop (latched here when the supervision is lost), no heartbeat yet (with
        supervision), or a pause by the launcher or by a human-input client whose pause has not expired."""
        self.check_supervision()
        return self.estop is not None or self.supervision.waiting or self.awaiting_ready is not None \
            or self.launcher_paused or self.human_pauses.active(time.monotonic())

    def check_supervision(self) -> None:
        """With supervision: latch the e-stop once the last heartbeat is older than the timeout (its ``sent``: when
        the timeout ran out, so the latency is the detection's)."""
        now = time.monotonic()
        silence = self.supervision.silence(now)
        if silence is None or self.estop is not None:
            return
        late = silence - self.supervision.timeout
        self.press_estop(f"the watchdog (no heartbeat from the supervisor for {silence:.2f} s)", time.time() - late,
                         self.episode)

    def restore_run_state(self, run_dir: str) -> None:
        """Before the first command: the run's e-stop state from ``RUN_DIR/estop.json`` (:meth:`restore`).

        :param run_dir: the run directory.
        """
        self.restore(read_state(run_dir), str(Path(run_dir) / STATE_FILE))

    def restore(self, state: dict | None, where: str) -> None:
        """Before the first command: the run's e-stop state from disk (:mod:`~khgrl.common.delivery.estop_state`).

        :param state: the state read (None: none), a pressed one latches the e-stop (its latency: from now).
        :param where: the file's path (for the log and the status).
        """
        if state is not None and state.get("pressed"):
            self.press_estop(f"the run's e-stop state ({where}: pressed by {state.get('by')})", time.time(), 0)

    @property
    def held_reason(self) -> str:
        """Why the actor is held by a command ("" when it is not): the e-stop first."""
        if self.estop is not None:
            return f"e-stop by {self.estop.by}" + (f" (also pressed by {', '.join(self.estop.also)})"
                                                   if self.estop.also else "")
        if self.supervision.waiting:
            return "waiting for the supervisor's heartbeat (khgrl up, or khgrl supervise RUN_DIR)"
        if self.launcher_paused:
            return "paused by the launcher"
        if self.human_pauses.active(time.monotonic()):
            return "paused by a human-input client"
        if self.awaiting_ready is not None:
            return f"waiting for ready before episode {self.awaiting_ready} (khgrl ready RUN_DIR, or r in a client)"
        return ""

    def ready(self, by: str) -> None:
        """A person says the robot is ready for the next episode (ignored, logged, when none waits for it).

        :param by: who.
        """
        if self.awaiting_ready is None:
            log.info("ready from %s ignored: no episode waits for it", by)
            return
        log.info("ready from %s: episode %d starts", by, self.awaiting_ready)
        self.awaiting_ready = None

    def press_estop(self, by: str, sent: float, episode: int) -> None:
        """The e-stop is pressed (the first press counts; a press while it is latched is logged).

        :param by: who pressed it.
        :param sent: the command's timestamp (the sender's ``time.time()``).
        :param episode: the actor's episode.
        """
        if self.estop is None:
            self.estop = EStop(by=by, sent=sent, episode=episode, t=int(self.p.env.t))
            log.warning("e-stop pressed by %s: the robot holds until `khgrl stop --release`", by)
        else:
            if by != self.estop.by and by not in self.estop.also:  # (named in the status: a client's press confirmed)
                self.estop.also.append(by)
                log.warning("e-stop pressed by %s (held already: e-stop by %s)", by, self.estop.by)

    def handle(self, kind: str, key: str, payload, arrival: float, episode: int) -> None:
        """One inbox item.

        :param kind: ``ack``, ``correction``, ``control``, ``human_request`` or ``alive``.
        :param key: the key it came on.
        :param payload: its bytes (``alive``: whether the token appeared).
        :param arrival: when it arrived (monotonic s).
        :param episode: the actor's current episode.
        """
        self.episode = episode
        if kind == "alive":
            self.on_alive(key, payload)
            return
        try:  # decoded, and checked against the key it came on (the sender's own)
            msg = read_for_actor(kind, key, payload, self.dims)
        except ProtocolError as exc:
            self.p.rejects.reject(getattr(exc, "kind", kind), key, exc)
            return
        if kind in ("control", "human_request") and (why := self.p.control.check(msg, key)):
            self.p.rejects.reject("control", key, ProtocolError(why))  # (unsigned, wrong key or role, a replay)
            return
        if kind == "ack":
            self._on_ack(msg, key)
        elif kind == "correction":
            if why := self.p.arbiter.offer(msg, arrival, episode, self.p.env.t):
                self.p.rejects.reject("correction", key, ProtocolError(why))
        elif kind == "human_request":  # a person's pause or resume (e.g. the GUI's space bar), on its own key
            self._on_human_request(msg, key, arrival, episode)
        else:
            self._on_control(msg, key, episode)

    def _on_human_request(self, msg: Control, key: str, arrival: float, episode: int) -> None:
        client = msg.envelope.sender
        if msg.command != "estop" and not self.p.arbiter.assignments.allows(client):  # (any client may press it)
            self.p.rejects.reject("control", key, ProtocolError(
                f"{msg.command} from human-input client {client!r}, not assigned to actor {self.p.arbiter.actor}"))
            return
        if msg.command == "estop":
            self.press_estop(f"human client {client}", msg.envelope.ts, episode)
        elif msg.command == "ready":
            self.ready(f"human client {client}")
        elif msg.command == "pause":
            if not self.human_pauses.holds(client):
                log.info("pause from human-input client %r (for %.0f s unless renewed)", client,
                         self.human_pauses.limit)
            self.human_pauses.pause(client, arrival)
        else:
            log.info("resume from human-input client %r", client)
            self.human_pauses.resume(client)

    def _on_ack(self, msg: Ack, key: str) -> None:
        stream, guard = self.p.stream, self.guard
        if msg.superseded and msg.stream == stream.stream and msg.actor == stream.actor:
            why = guard.authentic(msg) if guard.key is not None else None if guard.corroborated() else \
                "superseded ack ignored: not signed (no run key) and no ack of another stream of this id seen"
            if why:  # (a forged one would stop this actor)
                self.p.rejects.reject("ack", key, ProtocolError(why))
                return
        guard.on_ack(msg, stream.max_published, self.gate.epochs)
        if guard.fatal:
            self.flag.set("another process publishes as this actor")
            return
        if stream.on_ack(msg, key, check=lambda a: self.gate.implausible(a.epoch, a.version) or guard.authentic(a)):
            self.gate.note(msg.epoch, msg.version)
            guard.accepted()
        elif stream.superseded:  # another process runs this actor id: stop (exit 4)
            guard.superseded()
            self.flag.set("stream superseded")

    def on_alive(self, key: str, put: bool) -> None:
        """A learner's liveliness token appeared (``put``) or disappeared.

        :param key: its liveliness key.
        :param put: appeared.
        """
        if put:
            if key in self.guard.wrong:  # a learner of another task: not followed
                return
            if key not in self.learners and not self._admit_learner(key):
                return
            self.p.weights.receiver.learner_appeared(key)
            if key not in self.learners:
                self.learners.add(key)
                log.info("learner %s appeared (outbox: %d batches)", key, len(self.p.stream.outbox))
                self.check_learner_task()
                if key in self.learners:  # (not a learner of another task)
                    self.p.stream.learner_appeared()
        else:
            if key not in self.learners:
                return  # (one refused when it appeared)
            self.learners.discard(key)
            self.p.weights.receiver.learner_gone(key)
            log.warning("learner %s gone: acting on with weights version %d", key, self.p.weights.version)

    def check_learner_task(self) -> None:
        """Ignore the learners built for another task (counted, logged, not followed); the actor stops (exit 2) only
        when none of its own task comes (:meth:`~khgrl.common.delivery.actor_guard.ActorGuard.wrong_task`)."""
        if self.p.task is None:
            return
        wrong = self.p.link.other_tasks(self.p.task)
        ignored = {k: wrong[who[0]] for k in self.learners if (who := learner_of(k)) and who[0] in wrong}
        for k, why in ignored.items():
            self.learners.discard(k)
            self.p.weights.receiver.learner_gone(k)
            if k not in self.guard.wrong:
                self.p.rejects.reject("task", k, ProtocolError(f"learner ignored: {why}"))
        for k, why in ignored.items():
            self.guard.ignore(k, why, ours_alive=bool(self.learners))

    def _on_heartbeat(self, msg: Control, key: str, episode: int) -> None:
        """The supervisor's heartbeat: supervised; ``heartbeat-estop`` latches the e-stop (the run's state)."""
        if why := heartbeat_refusal(msg.envelope.sender):
            self.p.rejects.reject("control", key, ProtocolError(why))
            return
        now = time.monotonic()
        if self.supervision.beats == 0:
            log.info("supervised: first heartbeat from %s (e-stop %s)", msg.envelope.sender,
                     "pressed" if msg.command == HEARTBEAT_ESTOP else "released")
        self.supervision.beat(now)
        if msg.command == HEARTBEAT_ESTOP and self.estop is None and not self.supervision.stale_press(now):
            self.press_estop("the run's e-stop state (the supervisor's heartbeat)", msg.envelope.ts, episode)

    def _on_control(self, msg: Control, key: str, episode: int) -> None:
        if msg.command in HEARTBEATS:
            self._on_heartbeat(msg, key, episode)
            return
        attribute_control(msg, key, log)
        if msg.command == "estop":
            self.press_estop(msg.envelope.sender, msg.envelope.ts, episode)
        elif msg.command == "ready":
            self.ready(msg.envelope.sender)
        elif msg.command == "release":
            if self.estop is not None and self.estop.by == msg.envelope.sender and msg.envelope.ts <= self.estop.sent:
                log.warning("release from %s ignored: signed before the press it would release", msg.envelope.sender)
                return
            if self.estop is not None:
                log.warning("e-stop released by %s", msg.envelope.sender)
            self.estop = None
            self.supervision.released_at = time.monotonic()
        elif msg.command == "stop":
            self.flag.set("stop command")
        elif msg.command == "pause":
            self.launcher_paused = True
        elif msg.command == "resume":
            self.launcher_paused = False
