"""The protocol checks that hold without access control (docs/protocol.md, ``weights``, ``ack`` and ``control``),
without Zenoh: the actor's weights gate (learner epochs from liveliness, plausible versions, held weights), the
receiver and policy weights with the gate, acks with an implausible version, the actor's inbound handling (control
attribution, liveliness), and the learner's ``actor/<id>/request`` key. The same checks against real processes:
tests/integration/test_trust_checks.py."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest
from khgrl.actor.arbiter import CorrectionArbiter
from khgrl.actor.human_limits import Assignments
from khgrl.actor.inbound import Inbound
from khgrl.actor.weights import PolicyWeights, WeightsReceiver, WeightsUpdate
from khgrl.common.delivery.control_auth import ControlGate
from khgrl.common.delivery.trust import HOLD_S, MAX_VERSIONS_PER_S, VERSION_SLACK, WeightsGate, learner_of
from khgrl.common.process import StopFlag
from khgrl.common.wire.checks import ProtocolError, RejectCounter
from khgrl.common.wire.messages import Ack, Control, Dims, Weights
from khgrl.common.wire.protocol import Keys, encode

from test_actor_parts import Clock, collect, make_stream
from test_learner_parts import batch, make_loop

K = Keys("unit")
TOKEN = K.learner_alive("learner", "e1")


def update(version: int, epoch: str | None = "e1") -> WeightsUpdate:
    return WeightsUpdate(epoch=epoch, version=version, trained={}, state_dict={}, ts=0.0)


# ------------------------------------------------------------------------------------ keys
def test_learner_token_carries_its_epoch_and_the_pattern_matches_every_learner():
    assert TOKEN == "khgrl/unit/alive/learner/learner/e1"
    assert K.learners_alive == "khgrl/unit/alive/learner/**"
    assert K.request("a0") == "khgrl/unit/actor/a0/request" and K.request() == "khgrl/unit/actor/*/request"
    assert learner_of(TOKEN) == ("learner", "e1")
    assert learner_of(K.alive("learner", "old")) == ("old", None)  # a token without the epoch chunk
    assert learner_of(K.alive("actor", "a0")) is None and learner_of("khgrl/unit/alive/learner/a/b/c") is None


# ------------------------------------------------------------------------------------ the gate
def test_weights_only_of_an_epoch_whose_token_is_alive_held_until_it_appears():
    clock = Clock()
    gate = WeightsGate(clock)
    assert gate.admit(update(0)) is False and gate.held.version == 0  # version 0 comes before the token
    assert gate.admit(update(1)) is False and gate.held.version == 1  # the newest one only
    assert gate.take_dropped() == []  # (a newer one of the same epoch replaced it)
    released = gate.learner_appeared(TOKEN)
    assert released.version == 1 and gate.held is None and gate.epochs == {"e1"}
    assert gate.admit(update(2)) is True
    assert gate.admit(update(3, "made-up")) is False  # no token of that epoch: held, never loaded
    assert gate.admit(update(4, "another")) is False  # ...displaced by one of another epoch: counted
    assert gate.take_dropped() == ["weights version 3 of learner epoch made-up: no learner of that epoch appeared "
                                   "(weights of another epoch came)"]
    clock.t += HOLD_S + 0.1
    gate.expire()
    assert gate.held is None and len(gate.take_dropped()) == 1  # its learner never came
    gate.learner_gone(TOKEN)
    assert gate.admit(update(5)) is False  # the learner is gone: held until it comes back
    assert gate.learner_appeared(TOKEN).version == 5


def test_a_forged_high_version_is_refused_and_the_bound_grows_with_time():
    clock = Clock()
    gate = WeightsGate(clock)
    gate.learner_appeared(TOKEN)
    assert gate.admit(update(7))
    assert gate.ceiling("e1") == 7 + VERSION_SLACK and gate.ceiling("other") is None
    with pytest.raises(ProtocolError, match="version 1000000000 of learner epoch e1 is implausible"):
        gate.admit(update(10**9))
    with pytest.raises(ProtocolError, match="implausible"):
        gate.admit(update(7 + VERSION_SLACK + 1))
    assert gate.admit(update(7 + VERSION_SLACK))
    clock.t += 2.0  # two seconds later a learner can be 2 * MAX_VERSIONS_PER_S versions further
    assert gate.admit(update(7 + VERSION_SLACK + int(2 * MAX_VERSIONS_PER_S)))
    assert gate.implausible("e1", 10**9) and gate.implausible("never-seen", 10**9) is None


def test_the_lowest_ceiling_is_kept_so_a_forged_first_version_loosens_nothing():
    clock = Clock()
    gate = WeightsGate(clock)
    gate.learner_appeared(TOKEN)
    assert gate.admit(update(10**9))  # the first version of an epoch cannot be checked...
    gate.note("e1", 3)  # ...but a genuine ack of version 3 shows it up
    assert gate.implausible("e1", 10**9) and gate.implausible("e1", 4) is None
    with pytest.raises(ProtocolError):
        gate.admit(update(10**9 + 1))


def test_weights_without_an_epoch_are_refused_while_a_learner_with_one_is_followed():
    gate = WeightsGate(Clock())
    assert gate.admit(update(0, None)) is False  # nobody alive: held
    assert gate.learner_appeared(K.alive("learner", "old")).version == 0  # a learner without an epoch
    gate.learner_appeared(TOKEN)
    with pytest.raises(ProtocolError, match="without an epoch"):
        gate.admit(update(1, None))


# ------------------------------------------------------------------------------------ receiver and policy
class _Policy:
    def __init__(self) -> None:
        import torch

        self.actor = torch.nn.Linear(3, 2)

    def load_weights(self, sd) -> None:
        self.actor.load_state_dict(sd)


def _weights(version: int, epoch: str | None = "e1", fill: float = 1.0) -> bytes:
    tensors = {"weight": np.full((2, 3), fill, np.float32), "bias": np.zeros(2, np.float32)}
    return encode(Weights(version=version, trained={"a0": 8}, tensors=tensors, epoch=epoch), "learner", version)


def _policy_weights(clock) -> tuple[PolicyWeights, WeightsReceiver, RejectCounter]:
    policy = _Policy()
    rejects = RejectCounter("actor/a0")
    rx = WeightsReceiver(None, policy.actor.state_dict(), rejects, "k/weights")
    return PolicyWeights(policy, "a0", rx), rx, rejects


def test_receiver_counts_refused_weights_and_releases_held_ones(caplog):
    import torch

    w, rx, rejects = _policy_weights(Clock())
    rx.offer(_weights(0))  # before the gate is installed...
    rx.use_gate(WeightsGate(Clock()))  # ...checked again: its learner is not alive yet, so it is held
    assert rx.take() is None and rx.received == 0 and rx.gate.held.version == 0
    rx.learner_appeared(TOKEN)
    w.swap()
    assert (w.epoch, w.version) == ("e1", 0)
    with caplog.at_level(logging.WARNING):
        rx.offer(_weights(10**9, fill=9.0))  # forged: the real epoch, an impossible version
        rx.offer(_weights(5, epoch=None, fill=9.0))  # forged: no epoch
    w.swap()
    assert w.version == 0 and torch.all(w.policy.actor.weight == 1.0)
    assert rejects.by_kind() == {"weights": 2} and "implausible" in caplog.text and "without an epoch" in caplog.text
    w.load_replies([_weights(10**9 + 1, fill=9.0), _weights(1)])  # a query's replies go through the gate too
    assert w.version == 1 and rejects.by_kind() == {"weights": 3}


def test_loaded_weights_shown_implausible_are_replaced_by_a_genuine_lower_version():
    import torch

    clock = Clock()
    w, rx, _ = _policy_weights(clock)
    rx.use_gate(WeightsGate(clock))
    rx.learner_appeared(TOKEN)
    w.load_replies([_weights(10**9, fill=9.0)])  # a forger who won the race for the epoch's first version
    assert w.version == 10**9
    rx.offer(_weights(2))  # the learner's next weights
    w.swap()
    assert w.version == 2 and torch.all(w.policy.actor.weight == 1.0)
    assert not w.load(rx.parse(_weights(1)))  # an older genuine version is still older


def test_an_ack_with_an_implausible_version_is_refused(tmp_path):
    stream, _, _, rejects = make_stream(tmp_path)
    gate = WeightsGate(Clock())
    gate.note("e1", 3)
    collect(stream, 16)

    def check(a):
        return gate.implausible(a.epoch, a.version)

    forged = Ack(actor="a0", received=1, durable=1, trained=0, version=10**9, epoch="e1", stream="s1")
    assert not stream.on_ack(forged, "k/ack", check=check)
    assert stream.durable == -1 and stream.refused_acks == 1 and rejects.by_kind() == {"ack": 1}
    assert stream.on_ack(forged.replace(version=4), "k/ack", check=check)
    assert stream.durable == 1 and stream.ack_version == 4


# ------------------------------------------------------------------------------------ the actor's inbound
def _inbound(tmp_path) -> tuple[Inbound, SimpleNamespace, StopFlag]:
    stream, _, _, rejects = make_stream(tmp_path)
    w, rx, _ = _policy_weights(Clock())
    rx.rejects = rejects
    parts = SimpleNamespace(stream=stream, weights=w, rejects=rejects, env=SimpleNamespace(t=0),
                            control=ControlGate.of_run(None), task=None, link=None,
                            arbiter=CorrectionArbiter("a0", 0.5, enabled=True))
    flag = StopFlag()
    return Inbound(parts, flag, Dims(out=2)), parts, flag


def test_inbound_follows_learner_tokens_and_refuses_forged_acks(tmp_path):
    inbound, parts, _ = _inbound(tmp_path)
    rx = parts.weights.receiver
    rx.offer(_weights(0))
    assert rx.take() is None  # held: no token yet
    inbound.handle("alive", TOKEN, True, 0.0, episode=1)
    assert inbound.learners == {TOKEN} and inbound.gate.epochs == {"e1"}
    parts.weights.swap()
    assert parts.weights.version == 0
    collect(parts.stream, 16)
    real = Ack(actor="a0", received=1, durable=-1, trained=0, version=2, epoch="e1", stream="s1")
    inbound.handle("ack", K.ack("a0"), encode(real, "learner", 0), 0.0, episode=1)
    assert parts.stream.received == 1 and inbound.gate.ceiling("e1") < 10**6
    for forged in (real.replace(version=10**9), real.replace(received=50, durable=50)):
        inbound.handle("ack", K.ack("a0"), encode(forged, "learner", 1), 0.0, episode=1)
    assert parts.stream.refused_acks == 2 and parts.stream.durable == -1 and parts.stream.ack_version == 2
    inbound.handle("alive", TOKEN, False, 0.0, episode=1)
    assert not inbound.learners and inbound.gate.epochs == set()


@pytest.mark.parametrize("sender, level", [("operator", logging.WARNING), ("launcher", logging.INFO)])
def test_a_stop_or_pause_is_attributed(tmp_path, caplog, sender, level):
    inbound, _, flag = _inbound(tmp_path)
    with caplog.at_level(logging.INFO, logger="khgrl.actor"):
        inbound.handle("control", K.control("all"), encode(Control(command="pause"), sender, 0), 0.0, episode=1)
        inbound.handle("control", K.control("actor"), encode(Control(command="stop"), sender, 1), 0.0, episode=1)
    assert inbound.paused and flag and flag.reason == "stop command"
    lines = [r for r in caplog.records if "control" in r.getMessage()]
    assert [r.levelno for r in lines] == [level, level]
    assert f"'{sender}' on khgrl/unit/control/actor" in lines[1].getMessage()


# ------------------------------------------------------------------------------------ the learner
def test_learner_takes_only_a_checkpoint_request_from_the_actor_on_its_request_key(tmp_path, caplog):
    loop, _ = make_loop(tmp_path)
    loop.offer(batch(0, 0, 8))  # a0 is admitted (its batches are stored): its requests count (test_shares.py)
    loop.receive("request", K.request("a0"), encode(Control(command="checkpoint"), "a0", 0))
    assert loop.checkpoint_requested
    loop.checkpoint_requested = False
    with caplog.at_level(logging.WARNING):
        loop.receive("request", K.request("a0"), encode(Control(command="stop"), "a0", 1))
        loop.receive("request", K.request("a0"), encode(Control(command="pause"), "a0", 2))
        loop.receive("request", K.request("a0"), encode(Control(command="checkpoint"), "a1", 3))  # not its key
    assert not loop.flag and not loop.paused and not loop.checkpoint_requested
    assert loop.rejects.by_kind() == {"control": 3}
    assert "an actor may only request a checkpoint" in caplog.text and "sender 'a1' published on" in caplog.text


def test_learner_logs_who_stopped_it(tmp_path, caplog):
    loop, _ = make_loop(tmp_path)
    with caplog.at_level(logging.INFO, logger="khgrl.learner"):
        loop.receive("control", K.control("learner"), encode(Control(command="checkpoint"), "tool", 0))
        loop.receive("control", K.control("all"), encode(Control(command="stop"), "intruder", 0))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == ["control stop from 'intruder' on khgrl/unit/control/all: not from the launcher"]
    assert loop.flag.reason == "stop command" and loop.checkpoint_requested


def test_the_estop_is_latched_until_the_launchers_release_and_ready_only_counts_when_asked(tmp_path):
    """Any client's e-stop holds (assigned or not); only the launcher releases it; ready only when asked."""
    inbound, parts, _ = _inbound(tmp_path)
    human = K.human_request("kb")
    inbound.handle("human_request", human, encode(Control(command="ready"), "kb", 0), 0.0, episode=1)
    assert not inbound.paused  # a ready nobody waits for is ignored (not kept for later)
    inbound.handle("human_request", human, encode(Control(command="estop"), "kb", 1), 0.0, episode=1)
    assert inbound.paused and inbound.held_reason == "e-stop by human client kb"
    for key, sender in ((human, "kb"), (K.control("all"), "launcher")):  # a human's resume, the launcher's resume
        inbound.handle("human_request" if sender == "kb" else "control", key,
                       encode(Control(command="resume"), sender, 2), 0.0, episode=1)
    assert inbound.estop is not None and inbound.paused  # neither releases the e-stop
    inbound.handle("human_request", human, encode(Control(command="release"), "kb", 3), 0.0, episode=1)
    assert inbound.estop is not None and parts.rejects.by_kind() == {"control": 1}  # a human may not release it
    inbound.handle("control", K.control("actor"), encode(Control(command="release"), "launcher", 4), 0.0, episode=1)
    assert inbound.estop is None and not inbound.paused
    inbound.awaiting_ready = 2
    assert inbound.paused and inbound.held_reason.startswith("waiting for ready before episode 2")
    inbound.handle("human_request", human, encode(Control(command="ready"), "kb", 5), 0.0, episode=1)
    assert inbound.awaiting_ready is None and not inbound.paused
    parts.arbiter.assignments = Assignments("a0", "other=a0")  # kb is not assigned to this actor: its pause is
    inbound.handle("human_request", human, encode(Control(command="pause"), "kb", 6), 0.0, episode=1)
    assert not inbound.paused and parts.rejects.by_kind() == {"control": 2}  # refused, but its e-stop holds (issue 33)
    inbound.handle("human_request", human, encode(Control(command="estop"), "kb", 7), 0.0, episode=1)
    assert inbound.held_reason == "e-stop by human client kb" and parts.rejects.by_kind() == {"control": 2}


def test_supervision_heartbeats_the_estop_state_and_its_loss(tmp_path, monkeypatch):
    """Robot mode (issue 33): no step before a heartbeat; one from a sender other than the launcher is refused; a
    ``heartbeat-estop`` latches the e-stop, except just after a release; a silence beyond the timeout latches it, and
    the next heartbeat does not release it; the run's e-stop state on disk latches it before the first step."""
    from khgrl.actor.supervision import Supervision

    inbound, parts, _ = _inbound(tmp_path)
    inbound.supervision = Supervision(True, 0.4)
    now = [100.0]
    monkeypatch.setattr("khgrl.actor.inbound.time.monotonic", lambda: now[0])

    def beat(command: str, sender: str = "launcher", seq: int = 0) -> None:
        inbound.handle("control", K.control("actor"), encode(Control(command=command), sender, seq), 0.0, episode=1)

    assert inbound.paused and inbound.held_reason.startswith("waiting for the supervisor's heartbeat")
    beat("heartbeat", "intruder")
    assert inbound.supervision.waiting and parts.rejects.by_kind() == {"control": 1}
    beat("heartbeat")
    assert not inbound.paused
    beat("heartbeat-estop", seq=1)
    assert inbound.held_reason == "e-stop by the run's e-stop state (the supervisor's heartbeat)"
    beat("release", seq=2)
    beat("heartbeat-estop", seq=3)  # sent before the supervisor heard the release
    assert not inbound.paused
    now[0] += 0.41
    assert inbound.paused and inbound.held_reason.startswith("e-stop by the watchdog (no heartbeat from the supervisor")
    beat("heartbeat", seq=4)
    assert inbound.paused  # coming back does not release it
    beat("release", seq=5)
    assert not inbound.paused
    fresh, _, _ = _inbound(tmp_path)
    fresh.restore({"pressed": True, "by": "launcher"}, "RUN_DIR/estop.json")
    assert fresh.held_reason.startswith("e-stop by the run's e-stop state (RUN_DIR/estop.json: pressed by launcher")
