"""Issue 21, fake actor ids in plain mode: with the run's key every ``transitions`` batch carries a ``mac``
(:func:`~khgrl.common.delivery.run_key.batch_mac`), signed again when a re-send re-stamps its ``base_seq``, and a
learner with the key refuses a batch without a right one before it is stored or its actor id admitted (``mac``
rejects). Without the key nothing changes."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from khgrl.common.delivery import run_key
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.stream import TransitionStream
from khgrl.common.process import StopFlag
from khgrl.common.tasks.passage.env import PassageEnv
from khgrl.common.wire.checks import RejectCounter
from khgrl.common.wire.messages import Ack, Transitions
from khgrl.common.wire.protocol import Keys, decode, encode, with_base_seq
from khgrl.learner.loop import LearnerLoop, open_learner

from test_values import SMALL, _batch, _Pub

KEY, OTHER = b"k" * 32, b"o" * 32
KEYS = Keys("unit")


@pytest.fixture(scope="module")
def task():
    return PassageEnv("low_cov").descriptor("passage:low_cov")


def _loop(tmp_path, task, key: bytes | None) -> LearnerLoop:
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",), task=task)
    loop = LearnerLoop(trainer, streams, _Pub(), learner_id="learner", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag(), key=key)
    loop.set_task(task)
    return loop


def _signed(task, seq: int, actor: str = "a0", key: bytes | None = KEY, **over) -> bytes:
    return encode(run_key.sign_batch(_batch(task, seq, actor=actor, **over), key, seq), actor, seq)


def test_the_mac_covers_every_field_and_the_envelope_seq(task):
    b = _batch(task, 3)
    mac = run_key.batch_mac(b, KEY, 3)
    assert len(mac) == 32 and mac == run_key.batch_mac(b, KEY, 3)
    assert run_key.batch_mac(b, OTHER, 3) != mac and run_key.batch_mac(b, KEY, 4) != mac  # key, envelope seq
    changed = [b.replace(actor="a1"), b.replace(stream="s1"), b.replace(first_step=1), b.replace(base_seq=1),
               b.replace(task="f" * 16), b.replace(reward=b.reward + 1), b.replace(clipped=1 - b.clipped),
               b.replace(obs=b.obs[:4], next_obs=b.next_obs[:4], action=b.action[:4], reward=b.reward[:4],
                         terminated=b.terminated[:4], truncated=b.truncated[:4], intervened=b.intervened[:4],
                         clipped=b.clipped[:4])]
    assert all(run_key.batch_mac(c, KEY, 3) != mac for c in changed)
    got = decode(Transitions, _signed(task, 3))  # the wire keeps it; the receiver's check agrees
    assert got.mac == mac and run_key.check(got, KEY) is None and run_key.check(got, None) is None
    assert "wrong mac" in run_key.check(got, OTHER)
    assert "without a mac" in run_key.check(decode(Transitions, encode(b, "a0", 3)), KEY)
    with pytest.raises(Exception, match="mac"):  # a mac of another length is malformed
        encode(b.replace(mac=b"x" * 31), "a0", 3)


def test_a_re_stamped_batch_is_signed_again(task):
    payload = _signed(task, 5)
    stale = decode(Transitions, with_base_seq(payload, 2))  # re-stamped, not re-signed: no mac left
    assert stale.base_seq == 2 and stale.mac is None
    again = decode(Transitions, with_base_seq(payload, 2, lambda m: run_key.wire_batch_mac(m, KEY)))
    assert again.base_seq == 2 and run_key.check(again, KEY) is None
    forged = decode(Transitions, with_base_seq(payload, 2, lambda m: run_key.wire_batch_mac(m, OTHER)))
    assert "wrong mac" in run_key.check(forged, KEY)


def test_the_actor_stream_signs_what_it_sends_and_re_sends(task, tmp_path):
    sent: list[bytes] = []
    st = TransitionStream("a0", "s0", Outbox(100, tmp_path / "outbox"), sent.append, RejectCounter("t"),
                          task=task.digest, key=KEY, window=1)
    o = np.zeros(5, np.float32)
    for _ in range(3):  # batch 0 goes at once; 1 and 2 wait for the window (re-stamped when they go)
        st.add(o, o, np.zeros(2, np.float32), 0.0, False, False, False, False)
        st.cut()
    st.on_ack(Ack(actor="a0", received=0, durable=0, trained=0, version=0, epoch="e", stream="s0"))
    st.on_ack(Ack(actor="a0", received=1, durable=0, trained=0, version=0, epoch="e", stream="s0"))
    st.resend(-1, "test")  # everything held again, with the current base_seq
    got = [decode(Transitions, p) for p in sent]
    assert [m.envelope.seq for m in got] == [0, 1, 2, 1, 2]
    assert [m.base_seq for m in got[1:]] == [1, 1, 1, 1]  # (batch 0 dropped as durable: re-stamped)
    assert all(run_key.check(m, KEY) is None for m in got)
    plain: list[bytes] = []
    st = TransitionStream("a0", "s1", Outbox(100, tmp_path / "o2"), plain.append, RejectCounter("t"), task=task.digest)
    st.add(o, o, np.zeros(2, np.float32), 0.0, False, False, False, False)
    st.cut()
    assert decode(Transitions, plain[0]).mac is None  # no key: as before


def test_a_learner_with_the_key_refuses_unsigned_batches_before_admitting_their_ids(task, tmp_path, caplog):
    loop = _loop(tmp_path, task, KEY)
    with caplog.at_level(logging.WARNING, logger="khgrl.protocol"):
        for i in range(300):  # fake ids: no mac, a wrong one
            loop.receive("transitions", KEYS.transitions(f"f{i}"), _signed(task, 0, f"f{i}", key=None))
            loop.receive("transitions", KEYS.transitions(f"g{i}"), _signed(task, 0, f"g{i}", key=OTHER))
    assert loop.rejects.by_kind() == {"mac": 600} and loop.info().rejects == {"mac": 600}
    assert list(loop.streams) == [] and loop.trainer.total == 0 and not loop.ingest.admitted("f0")
    assert "actor f0 batch 0: transitions without a mac" in caplog.text
    assert caplog.text.count("transitions without a mac") < 20  # rate-limited
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0))
    assert list(loop.streams) == ["a0"] and loop.trainer.total == 8
    # a signed batch re-published with another base_seq (not signed again) is refused too
    loop.receive("transitions", KEYS.transitions("a0"), with_base_seq(_signed(task, 1), 1))
    assert loop.rejects.by_kind() == {"mac": 601} and loop.trainer.total == 8


def test_a_learner_without_the_key_takes_batches_as_before(task, tmp_path):
    loop = _loop(tmp_path, task, None)
    loop.receive("transitions", KEYS.transitions("a0"), _signed(task, 0, key=None))
    loop.receive("transitions", KEYS.transitions("a1"), encode(run_key.sign_batch(
        _batch(task, 7, actor="a1", first_step=0), KEY, 0), "a1", 0))  # a mac is not looked at
    assert sorted(loop.streams) == ["a0", "a1"] and loop.trainer.total == 16 and loop.rejects.by_kind() == {}
