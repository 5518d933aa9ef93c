"""Issue 34 (3, 4): acks, weights and batches signed per role. With the run's role keys the learner signs acks and
weights as ``learner:<id>`` and each actor its batches as ``actor:<id>``; a receiver with ``public.json`` takes
them only so signed, so the holder of one role's key (and the shared run key) cannot speak as another. Two
different batches signed by one actor for one (stream, seq) raise the split-brain alarm; the first is kept."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.delivery import data_keys, run_key
from khgrl.common.delivery.actor_guard import ActorGuard
from khgrl.common.delivery.data_keys import DataKeys
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.role_keys import make_run_keys
from khgrl.common.delivery.stream import TransitionStream
from khgrl.common.delivery.trust import WeightsGate
from khgrl.common.process import StopFlag
from khgrl.common.tasks.passage.env import PassageEnv
from khgrl.common.wire.checks import ProtocolError, RejectCounter
from khgrl.common.wire.messages import Ack, Transitions, Weights
from khgrl.common.wire.protocol import Keys, decode, encode, with_base_seq
from khgrl.learner.loop import LearnerLoop, open_learner

from test_values import SMALL, _batch, _Pub

RUN_KEY = b"k" * 32
KEYS = Keys("unit")


@pytest.fixture(scope="module")
def task():
    return PassageEnv("low_cov").descriptor("passage:low_cov")


@pytest.fixture()
def run(tmp_path):
    """A run directory with the run key and role keys for learner l0 and actors a0, a1."""
    (tmp_path / run_key.KEY_FILE).write_bytes(RUN_KEY)
    (tmp_path / run_key.KEY_FILE).chmod(0o600)
    make_run_keys(tmp_path, [("learner", "l0"), ("actor", "a0"), ("actor", "a1")], fresh=True)
    return tmp_path


def _keys(run, role: str, ident: str) -> DataKeys:
    keys = DataKeys.of_run(run, role, ident)
    assert keys is not None and keys.private is not None and keys.checking and keys.run == RUN_KEY
    return keys


def _ack(**over) -> Ack:
    fields = dict(actor="a0", received=3, durable=3, trained=0, version=5, epoch="e1", stream="s0")
    fields.update(over)
    return Ack(**fields)


def _weights(version: int = 7) -> Weights:
    return Weights(version=version, trained={"a0": 8}, tensors={"w": np.ones((2, 3), np.float32)}, epoch="e1")


def _wire(msg, sender="l0", seq=0):
    return decode(type(msg), encode(msg, sender, seq))


def test_acks_and_weights_are_taken_only_signed_by_the_learner(run):
    learner, a0, a1 = _keys(run, "learner", "l0"), _keys(run, "actor", "a0"), _keys(run, "actor", "a1")
    guard, gate = ActorGuard("a0", "s0", a0), WeightsGate(key=a0)
    good_ack, good_w = _wire(data_keys.sign(_ack(), learner)), _wire(data_keys.sign(_weights(), learner))
    assert good_ack.signer == "learner:l0" and len(good_ack.sig) == 64 and good_ack.mac is not None
    assert guard.authentic(good_ack) is None
    gate.authentic(good_w)  # (raises if refused)
    # actor a1 holds the run key and its own role key: its mac is right, its signature is not the learner's
    forged_ack = _wire(data_keys.sign(_ack(superseded=True), a1))
    assert run_key.check(forged_ack, RUN_KEY) is None  # what made it pass before
    assert "signed by 'actor:a1', not by a learner" in guard.authentic(forged_ack)
    with pytest.raises(ProtocolError, match="not by a learner"):
        gate.authentic(_wire(data_keys.sign(_weights(126), a1)))
    # the run key alone (no signature) or a signer field that lies about who signed
    assert "not signed" in guard.authentic(_wire(run_key.sign(_ack(), RUN_KEY)))
    lying = _wire(run_key.sign(_ack(), RUN_KEY).replace(signer="learner:l0", sig=a1.private.sign(b"x")))
    assert "wrong signature for 'learner:l0'" in guard.authentic(lying)
    # a changed field after signing
    changed = _wire(data_keys.sign(_ack(), learner).replace(durable=9))
    assert "wrong mac" in guard.authentic(changed)
    changed = _wire(run_key.sign(data_keys.sign(_ack(), learner).replace(durable=9), RUN_KEY))
    assert "wrong signature" in guard.authentic(changed)
    # the expected learner id, when the actor knows it
    other = DataKeys(run=RUN_KEY, kid="actor:a0", private=a0.private, public=a0.public, peer="learner:l9")
    assert "not by learner:l9" in data_keys.check(good_ack, other)


def test_a_process_without_role_keys_behaves_as_before(tmp_path, run):
    assert DataKeys.of_run(tmp_path / "none", "actor", "a0") is None
    (tmp_path / "k").mkdir()
    (tmp_path / "k" / run_key.KEY_FILE).write_bytes(RUN_KEY)
    only_run = DataKeys.of_run(tmp_path / "k", "actor", "a0")
    assert only_run.run == RUN_KEY and not only_run.checking and only_run.private is None
    ack = _wire(data_keys.sign(_ack(), only_run))
    assert ack.sig is None and data_keys.check(ack, only_run) is None and data_keys.check(ack, RUN_KEY) is None
    signed = _wire(data_keys.sign(_ack(), _keys(run, "learner", "l0")))
    assert data_keys.check(signed, RUN_KEY) is None and data_keys.check(signed, None) is None


def _loop(tmp_path, task, key) -> LearnerLoop:
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",), task=task)
    loop = LearnerLoop(trainer, streams, _Pub(), learner_id="l0", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag(), key=key)
    loop.set_task(task)
    return loop


def _signed(task, seq: int, keys, actor: str = "a0", **over) -> bytes:
    return encode(data_keys.sign_batch(_batch(task, seq, actor=actor, **over), keys, seq), actor, seq)


def test_a_batch_is_taken_only_signed_by_its_own_actor(task, run, tmp_path):
    a0, a1 = _keys(run, "actor", "a0"), _keys(run, "actor", "a1")
    loop = _loop(tmp_path, task, _keys(run, "learner", "l0"))
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, a1))  # a1's key, a0's stream
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, RUN_KEY))  # the run key only
    assert loop.rejects.by_kind() == {"sig": 2} and list(loop.streams) == [] and loop.trainer.total == 0
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, a0))
    loop.receive("transitions", KEYS.transitions("a1"), _signed(task, 0, a1, actor="a1",
                                                                       reward=np.arange(8, dtype=np.float32)))
    assert sorted(loop.streams) == ["a0", "a1"] and loop.trainer.total == 16
    # re-stamped: the signature no longer matches unless the actor signs it again
    loop.receive("transitions", KEYS.transitions("a0"), with_base_seq(_signed(task, 1, a0), 1,
                                                                      lambda m: run_key.wire_batch_mac(m, RUN_KEY)))
    assert loop.rejects.by_kind() == {"sig": 3} and loop.trainer.total == 16
    loop.receive("transitions", KEYS.transitions("a0"), with_base_seq(_signed(task, 1, a0), 1,
                                                                      lambda m: data_keys.wire_sign(m, a0)))
    assert loop.trainer.total == 24 and loop.info().alarm == ""


def test_two_different_batches_signed_for_one_seq_raise_the_split_brain_alarm(task, run, tmp_path):
    a0 = _keys(run, "actor", "a0")
    loop = _loop(tmp_path, task, _keys(run, "learner", "l0"))
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, a0))
    stored = loop.trainer.buffer.rewards[:8].copy() if hasattr(loop.trainer.buffer, "rewards") else None
    # the same batch again, and re-stamped with a newer base_seq: a re-send, not a conflict
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, a0))
    loop.receive("transitions", KEYS.transitions("a0"), with_base_seq(_signed(task, 0, a0), 0,
                                                                      lambda m: data_keys.wire_sign(m, a0)))
    assert loop.rejects.by_kind() == {} and loop.info().alarm == ""
    forged = _signed(task, 0, a0, reward=np.full(8, 100.0, np.float32))  # validly signed, other contents
    loop.receive("transitions", KEYS.transitions("a0"), forged)
    info = loop.info()
    assert loop.rejects.by_kind() == {"conflict": 1} and "split brain" in info.alarm and "seq 0" in info.alarm
    assert loop.trainer.total == 8 and loop.ingest.signed.conflicts == 1
    if stored is not None:
        assert np.array_equal(loop.trainer.buffer.rewards[:8], stored)  # the first is kept


def test_the_actor_stream_signs_each_batch_and_each_re_send(task, run, tmp_path):
    a0 = _keys(run, "actor", "a0")
    sent: list[bytes] = []
    st = TransitionStream("a0", "s0", Outbox(100, tmp_path / "outbox"), sent.append, RejectCounter("t"),
                          task=task.digest, key=a0, window=1)
    o = np.zeros(5, np.float32)
    for _ in range(3):
        st.add(o, o, np.zeros(2, np.float32), 0.0, False, False, False, False)
        st.cut()
    st.on_ack(Ack(actor="a0", received=0, durable=0, trained=0, version=0, epoch="e", stream="s0"))
    st.on_ack(Ack(actor="a0", received=1, durable=0, trained=0, version=0, epoch="e", stream="s0"))
    st.resend(-1, "test")
    got = [decode(Transitions, p) for p in sent]
    learner = _keys(run, "learner", "l0")
    assert [m.envelope.seq for m in got] == [0, 1, 2, 1, 2] and all(m.signer == "actor:a0" for m in got)
    assert all(data_keys.check(m, learner) is None for m in got)
    assert [m.base_seq for m in got[1:]] == [1, 1, 1, 1]  # re-stamped and signed again


def test_the_learner_alarm_ends_the_run_like_an_actor_alarm(task, run, tmp_path, capsys):
    from khgrl.common.wire.messages import Status
    from khgrl.deploy.run import outcome

    a0 = _keys(run, "actor", "a0")
    loop = _loop(tmp_path, task, _keys(run, "learner", "l0"))
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, a0))
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, a0, reward=np.ones(8, np.float32)))
    status = decode(Status, encode(Status(role="learner", info=loop.info()), "l0", 0))  # (the alarm on the wire)
    out = outcome.Outcome()
    outcome.actor_alarm(out, status, "status/learner/l0")
    assert out.error.startswith("learner l0: split brain: two different batches signed by actor:a0"), out.error
    assert "ending the run" in capsys.readouterr().err
