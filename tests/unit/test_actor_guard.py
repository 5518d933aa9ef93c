"""The run key's ``mac`` on acks and weights, and what an actor concludes from its acks and the learners alive
(:mod:`khgrl.common.delivery.run_key`, :mod:`khgrl.common.delivery.actor_guard`). Real processes:
tests/integration/test_attack_split.py."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest
from khgrl.common.delivery import run_key
from khgrl.common.delivery.actor_guard import BEYOND_ACKS, TWO_LEARNERS_S, ActorGuard
from khgrl.common.delivery.control_auth import ControlGate
from khgrl.common.wire.messages import Ack, Weights
from khgrl.common.wire.protocol import decode, encode


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


KEY = bytes(range(32))
ACK = Ack(actor="a0", received=5, durable=3, trained=40, version=7, epoch="e1", stream="s1", task="d")


def test_the_key_file_is_private_and_kept_unless_fresh(tmp_path):
    assert run_key.load(tmp_path) is None and run_key.load(None) is None
    key = run_key.create(tmp_path)
    path = tmp_path / run_key.KEY_FILE
    assert len(key) == 32 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert run_key.create(tmp_path) == key == run_key.load(tmp_path)
    assert run_key.create(tmp_path, fresh=True) != key
    path.write_bytes(b"short")
    with pytest.raises(run_key.RunKeyError):
        run_key.load(tmp_path)
    os.chmod(path, 0o600)


def test_a_signed_ack_and_weights_survive_the_wire_and_any_change_breaks_the_mac():
    signed = run_key.sign(ACK, KEY)
    back = decode(Ack, encode(signed, "learner", 0))
    assert back.mac == signed.mac and run_key.check(back, KEY) is None
    assert run_key.check(back, None) is None  # no key: nothing checked
    assert "without a mac" in run_key.check(ACK, KEY)
    for change in ({"durable": 5}, {"superseded": True}, {"stream": "s2"}, {"epoch": "e2"}):
        assert "wrong mac" in run_key.check(back.replace(**change), KEY), change
    assert "wrong mac" in run_key.check(back, bytes(32))
    w = Weights(version=3, trained={"a0": 8}, tensors={"b": np.ones(3, np.float32), "a": np.zeros((2, 2), np.float32)},
                epoch="e1")
    sw = decode(Weights, encode(run_key.sign(w, KEY), "learner", 0))
    assert run_key.check(sw, KEY) is None
    bad = dict(sw.tensors, b=np.array([1, 1, 2], np.float32))
    assert "wrong mac" in run_key.check(sw.replace(tensors=bad), KEY)
    assert "wrong mac" in run_key.check(sw.replace(version=4), KEY)


def test_one_ack_beyond_what_was_sent_is_not_a_split_brain_a_run_of_them_is():
    clock = Clock()
    g = ActorGuard("a0", "s1", None, clock)
    beyond = ACK.replace(received=9)
    g.on_ack(beyond, max_published=8, live_epochs={"e1"})  # one forged or raced ack
    g.accepted()  # then a good one
    for _ in range(BEYOND_ACKS + 2):
        g.on_ack(beyond, 8, {"e1"})  # at once: not over BEYOND_SPAN_S yet
    assert g.fatal is None
    g.on_ack(beyond, 8, {"e2"})  # an epoch not alive does not count
    assert g.fatal is None
    clock.t += 1.0
    g.on_ack(beyond, 8, {"e1"})
    assert g.fatal and "another process publishes as actor a0" in g.fatal and "stream id s1" in g.fatal
    assert "seq 9" in g.fatal and "up to seq 8" in g.fatal and g.alarm == g.fatal


def test_with_the_key_only_signed_acks_count():
    clock = Clock()
    g = ActorGuard("a0", "s1", KEY, clock)
    for _ in range(5):
        g.on_ack(ACK.replace(received=9), 8, {"e1"})
        clock.t += 1.0
    assert g.fatal is None
    for _ in range(BEYOND_ACKS):
        g.on_ack(run_key.sign(ACK.replace(received=9), KEY), 8, {"e1"})
        clock.t += 0.3
    assert g.fatal


def test_acks_of_another_stream_of_this_id_moving_forward_are_another_process():
    g = ActorGuard("a0", "s1", None, Clock())
    other = ACK.replace(stream="s2", received=3)
    g.on_ack(other, 8, {"e1"})
    g.on_ack(other, 8, {"e1"})  # the learner acking an old stream again: not moving
    g.on_ack(other.replace(received=4), 8, {"e1"})
    assert g.fatal is None
    g.on_ack(other.replace(received=5), 8, {"e1"})
    assert g.fatal and "another stream id s2 (this process: stream s1)" in g.fatal


def test_two_learner_epochs_alive_raise_the_alarm_after_a_while_vouched_ones_only_with_the_key():
    clock = Clock()
    g = ActorGuard("a0", "s1", None, clock)
    two = {"k/alive/learner/learner/e1": "e1", "k/alive/learner/learner/e2": "e2"}
    g.learners(two, set())
    clock.t += TWO_LEARNERS_S / 2
    g.learners({"k/alive/learner/learner/e1": "e1"}, set())  # a restart's overlap: gone again
    g.learners(two, set())
    clock.t += TWO_LEARNERS_S / 2
    g.learners(two, set())
    assert g.alarm is None
    clock.t += TWO_LEARNERS_S
    g.learners(two, set())
    assert g.alarm and "two learners" in g.alarm and g.fatal is None
    keyed = ActorGuard("a0", "s1", KEY, clock)
    for _ in range(3):
        keyed.learners(two, {"e1"})  # e2 signed nothing: a token anyone can declare
        clock.t += TWO_LEARNERS_S
    assert keyed.alarm is None
    keyed.learners(two, {"e1", "e2"})
    clock.t += TWO_LEARNERS_S
    keyed.learners(two, {"e1", "e2"})
    assert keyed.alarm


def test_a_learner_of_another_task_stops_the_actor_only_if_none_of_its_own_comes():
    clock = Clock()
    g = ActorGuard("a0", "s1", None, clock)
    g.ignore("k/alive/learner/evil/x", "learner evil was built for task 'other'", ours_alive=True)
    clock.t += 100
    assert g.wrong_task(True, 10.0) is None
    g.ignore("k/alive/learner/evil/x", "learner evil was built for task 'other'", ours_alive=False)
    clock.t += 5
    assert g.wrong_task(False, 10.0) is None
    clock.t += 6
    why = g.wrong_task(False, 10.0)
    assert why and "task 'other'" in why and "no learner of this actor's task came within 10 s" in why


def test_after_an_ack_beyond_what_was_sent_the_learner_is_asked_again_for_a_while():
    clock = Clock()
    g = ActorGuard("a0", "s1", None, clock)
    assert not g.probe_due()
    g.on_ack(ACK.replace(received=9), 8, {"e1"})
    assert g.probe_due() and not g.probe_due()  # at most every BEYOND_PROBE_S
    clock.t += 0.6
    assert g.probe_due()
    clock.t += 5.0  # the last such ack is old: no more asking
    assert not g.probe_due()
    g.on_ack(ACK.replace(received=9), 8, {"e1"})
    g.accepted()  # a genuine ack answered: the run is broken
    clock.t += 1.0
    assert not g.probe_due()


# ------------------------------------------------------------------------------------ the actor's inbound
def _inbound(tmp_path, key=None, tasks=None):
    from types import SimpleNamespace

    from khgrl.actor.inbound import Inbound
    from khgrl.common.process import StopFlag
    from khgrl.common.wire.messages import Dims

    from test_trust_checks import CorrectionArbiter, _policy_weights, make_stream

    stream, _, _, rejects = make_stream(tmp_path)
    w, rx, _ = _policy_weights(Clock())
    rx.rejects = rejects
    link = SimpleNamespace(other_tasks=lambda mine: dict(tasks or {}))
    parts = SimpleNamespace(stream=stream, weights=w, rejects=rejects, env=SimpleNamespace(t=0),
                            control=ControlGate.of_run(None), task=tasks and "t",
                            link=link, arbiter=CorrectionArbiter("a0", 0.5, enabled=True))
    flag = StopFlag()
    guard = ActorGuard("a0", stream.stream, key)
    return Inbound(parts, flag, Dims(out=2), guard=guard), parts, flag


TOKEN = "khgrl/unit/alive/learner/learner/e1"


@pytest.mark.parametrize("key", [None, KEY])
def test_a_forged_superseded_or_durable_ack_stops_nothing_and_drops_nothing(tmp_path, key):
    from khgrl.common.wire.protocol import Keys

    from test_trust_checks import collect

    inbound, parts, flag = _inbound(tmp_path, key)
    inbound.handle("alive", TOKEN, True, 0.0, episode=1)
    collect(parts.stream, 16)
    k = Keys("unit").ack("a0")
    sup = Ack(actor="a0", received=-1, durable=-1, trained=0, version=0, epoch="e1", stream="s1", superseded=True)
    inbound.handle("ack", k, encode(sup, "learner", 0), 0.0, episode=1)
    assert not flag and parts.rejects.by_kind() == {"ack": 1}
    durable = Ack(actor="a0", received=1, durable=1, trained=0, version=0, epoch="e1", stream="s1")
    inbound.handle("ack", k, encode(durable, "learner", 1), 0.0, episode=1)
    assert parts.stream.durable == (-1 if key else 1)  # without the key it is taken (plain mode trusts the router)
    if key is None:
        return
    assert len(parts.stream.outbox) == 2 and parts.stream.refused_acks == 1
    inbound.handle("ack", k, encode(run_key.sign(sup, KEY), "learner", 2), 0.0, episode=1)
    assert flag and inbound.guard.fatal and "the learner took another stream of this id" in inbound.guard.fatal


def test_an_unsigned_superseded_is_taken_once_another_stream_of_this_id_was_acked(tmp_path):
    from khgrl.common.wire.protocol import Keys

    from test_trust_checks import collect

    inbound, parts, flag = _inbound(tmp_path)
    inbound.handle("alive", TOKEN, True, 0.0, episode=1)
    collect(parts.stream, 16)
    k = Keys("unit").ack("a0")
    other = Ack(actor="a0", received=3, durable=-1, trained=0, version=0, epoch="e1", stream="s2")
    inbound.handle("ack", k, encode(other, "learner", 0), 0.0, episode=1)
    assert not flag
    sup = Ack(actor="a0", received=-1, durable=-1, trained=0, version=0, epoch="e1", stream="s1", superseded=True)
    inbound.handle("ack", k, encode(sup, "learner", 1), 0.0, episode=1)
    assert flag and "another process publishes as actor a0" in inbound.guard.fatal


def test_a_learner_of_another_task_is_ignored_not_followed(tmp_path):
    inbound, parts, flag = _inbound(tmp_path, tasks={"evil": "learner evil was built for task 'other'"})
    evil = "khgrl/unit/alive/learner/evil/x"
    inbound.handle("alive", evil, True, 0.0, episode=1)
    assert not flag and not inbound.learners and evil in inbound.guard.wrong and inbound.gate.epochs == set()
    assert parts.rejects.by_kind() == {"task": 1}
    inbound.handle("alive", evil, True, 0.0, episode=1)  # again: still ignored, counted once
    assert not inbound.learners and parts.rejects.by_kind() == {"task": 1}
