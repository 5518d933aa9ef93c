"""Human data vouched for by a human (issue 34, point 6): signed corrections (human_bridge/client.py), the evidence
an actor ships per intervened row (common/delivery/stream.py, common/wire/batch.py), the learner's check
(common/delivery/vouching.py) and the replay guard that now exempts only vouched batches (common/delivery/guards.py,
learner_side.py). Before: every row flagged ``intervened`` was prior data and exempt from the replay guard."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery import data_keys, run_key
from khgrl.common.delivery.data_keys import DataKeys
from khgrl.common.delivery.guards import ReplayGuard, batch_digest
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.role_keys import PublicKeys, load_private, make_run_keys
from khgrl.common.delivery.stream import TransitionStream
from khgrl.common.delivery.vouching import DEMO, ROWS_PER_WORD, Vouching, correction_bytes, evidence, sign_correction
from khgrl.common.process import StopFlag
from khgrl.common.wire.messages import Ack, Correction, Transitions
from khgrl.common.wire.protocol import ProtocolError, decode, encode, with_base_seq
from khgrl.learner.loop import LearnerLoop, open_learner

TASK = "0123456789abcdef"


@pytest.fixture
def run(tmp_path):
    """A run directory with role keys for the learner, a0, f1 and the human clients ``scripted`` and ``user``."""
    make_run_keys(tmp_path, [("learner", "learner"), ("actor", "a0"), ("actor", "f1"), ("human", "scripted")],
                  fresh=True)
    return tmp_path


def _word(run, actor: str = "a0", seq: int = 7, client: str = "scripted", key: str | None = None) -> Correction:
    """A correction of ``client`` for ``actor``, signed with ``key`` (default: its own), as the actor receives it."""
    msg = Correction(client=client, actor=actor, active=True, p_h=np.array([0.25, -1.5]), episode=3, t=4, step=5)
    signed = sign_correction(msg, load_private(run, key or f"human:{client}"), seq)
    return decode(Correction, encode(signed, client, seq))


def _batch(n: int = 4, actor: str = "a0", first: int = 0, iv=None, vouch=None, seq: int = 0,
           seed: int = 0) -> Transitions:
    rng = np.random.default_rng(seed)
    obs = rng.uniform(0, 1, (n, 5)).astype(np.float32)
    msg = Transitions(actor=actor, first_step=first, obs=obs, next_obs=obs[::-1].copy(),
                      action=rng.uniform(-1, 1, (n, 2)).astype(np.float32), reward=np.ones(n, np.float32),
                      terminated=np.zeros(n, np.uint8), truncated=np.zeros(n, np.uint8),
                      intervened=np.asarray(np.ones(n) if iv is None else iv, np.uint8),
                      clipped=np.zeros(n, np.uint8), base_seq=0, stream=f"s-{actor}", task=TASK, vouch=vouch)
    return decode(Transitions, encode(msg, actor, seq))


def _vouching(run, demo_limit: int = 0) -> Vouching:
    return Vouching(PublicKeys(run), demo_limit)


# ------------------------------------------------------------------------------------ signed corrections
def test_a_correction_signature_covers_its_fields_its_actor_and_its_seq(run):
    word = _word(run)
    pub = PublicKeys(run)
    fields = ("scripted", "a0", True, word.p_h, 3, 4, 5, 7)
    assert pub.verify("human:scripted", word.sig, correction_bytes(*fields)) is None
    for i, other in ((1, "f1"), (3, np.array([0.25, -1.5 + 2 ** -40])), (7, 8)):  # another actor, P_h, seq
        changed = list(fields)
        changed[i] = other
        assert pub.verify("human:scripted", word.sig, correction_bytes(*changed)) == "wrong signature for " \
                                                                                    "'human:scripted'"


def test_correction_sig_is_checked_on_the_wire():
    msg = Correction(client="c", actor="a0", active=False, sig=b"x" * 63)
    with pytest.raises(ProtocolError, match="sig: 63 bytes"):
        encode(msg, "c", 0)
    assert sign_correction(msg.replace(sig=None), None, 0).sig is None  # (no key: unsigned, as before)


# ------------------------------------------------------------------------------------ evidence on the wire
def test_evidence_is_the_signed_word_or_the_demo_mark_and_round_trips(run):
    word = _word(run)
    e = evidence(2, word)
    assert e == (2, "scripted", 7, 3, 4, 5, (0.25, -1.5), word.sig)
    assert evidence(0, DEMO) == (0,)
    assert evidence(1, None) is None and evidence(1, word.replace(sig=None)) is None
    msg = _batch(vouch=((0,), e))
    assert msg.vouch == ((0,), e)
    size = len(encode(msg, "a0", 0)) - len(encode(msg.replace(vouch=None), "a0", 0))
    assert size < 130  # (the demo entry 2 B; a signed word's about 110 B)


@pytest.mark.parametrize("vouch, why", [
    ([[4]], "row: 4 > 3"), ([[1], [1]], "row: 1 < 2"), ([[0, "c"]], "expected \\[row\\]"),
    ([[0, "c", 1, 1, 1, None, [], b"s" * 64]], "p_h: expected 1.."),
    ([[0, "c", 1, 1, 1, None, [float("nan")], b"s" * 64]], "p_h\\[0\\]"),
    ([[0, "c/x", 1, 1, 1, None, [0.5], b"s" * 64]], "client: bad identifier"),
    ([[0, "c", 1, 1, 1, None, [0.5], b"s" * 3]], "sig: 3 bytes")])
def test_bad_evidence_is_a_protocol_error(vouch, why):
    m = msgpack.unpackb(encode(_batch(), "a0", 0), raw=False)
    m["vouch"] = vouch
    with pytest.raises(ProtocolError, match=why):
        decode(Transitions, msgpack.packb(m, use_bin_type=True))


def test_the_batch_signature_covers_the_evidence_and_a_restamped_resend_keeps_it(run):
    keys = DataKeys(run=b"k" * 32, kid="actor:a0", private=load_private(run, "actor:a0"), public=PublicKeys(run))
    e = evidence(1, _word(run))
    msg = _batch(vouch=(e,)).replace(envelope=None)
    got = decode(Transitions, encode(data_keys.sign_batch(msg, keys, 3), "a0", 3))
    assert data_keys.check(got, keys) is None
    stripped = got.replace(vouch=None)
    assert "wrong signature" in data_keys.check_sig(stripped, keys)  # (removing or adding evidence breaks it)
    again = decode(Transitions, with_base_seq(encode(data_keys.sign_batch(msg, keys, 3), "a0", 3), 2,
                                              lambda m: data_keys.wire_sign(m, keys)))
    assert again.base_seq == 2 and again.vouch == (e,) and data_keys.check(again, keys) is None
    for vouch in (None, (e,)):  # the mac of a batch as a message and as its map (re-stamped) agree
        m = _batch(vouch=vouch).replace(envelope=None)
        assert run_key.batch_mac(m, b"k" * 32, 0) == run_key.wire_batch_mac(msgpack.unpackb(encode(m, "a0", 0)),
                                                                            b"k" * 32)


def test_the_actor_stream_ships_evidence_for_intervened_rows_only(run):
    from khgrl.common.wire.checks import RejectCounter

    sent: list[bytes] = []
    stream = TransitionStream("a0", "s", Outbox(100, run / "outbox"), sent.append, RejectCounter("a0"), task=TASK)
    word, obs = _word(run), np.zeros(5, np.float32)
    for i, (iv, w) in enumerate([(True, word), (False, word), (True, None), (True, DEMO), (True, word.replace(
            sig=None))]):
        stream.add(obs + i, obs, np.zeros(2, np.float32), 0.0, False, False, iv, False, w)
    stream.cut()
    msg = decode(Transitions, sent[0])
    assert [e[0] for e in msg.vouch] == [0, 3] and msg.vouch[1] == (3,) and msg.vouch[0][-1] == word.sig
    stream.add(obs, obs, np.zeros(2, np.float32), 0.0, False, False, False, False)
    stream.cut()
    assert decode(Transitions, sent[1]).vouch is None  # (none: the field is left out)


# ------------------------------------------------------------------------------------ the learner's check
def test_without_role_keys_the_flag_counts_as_before(tmp_path):
    v = Vouching(PublicKeys(tmp_path)).judge(_batch())
    assert v.vouched == 4 and v.unvouched == 0 and v.all_vouched and v.batch.intervened.all()


def test_rows_with_a_human_signature_for_this_actor_are_prior_data_the_rest_ordinary(run):
    e = evidence(1, _word(run))
    v = _vouching(run).judge(_batch(iv=[0, 1, 1, 0], vouch=(e,)))
    assert (v.vouched, v.unvouched, v.all_vouched) == (1, 1, False)
    assert v.batch.intervened.tolist() == [0, 1, 0, 0] and v.why == "no evidence"


def test_evidence_for_another_actor_or_by_another_key_vouches_for_nothing(run):
    vouching = _vouching(run)
    for word, why in ((_word(run, actor="a0"), "wrong signature"),  # a0's word attached to f1's row
                      (_word(run, actor="f1", key="actor:f1"), "wrong signature"),  # f1 signs as the human
                      (_word(run, actor="f1", client="ghost", key="human:scripted"), "not know")):
        v = vouching.judge(_batch(actor="f1", iv=[1, 0, 0, 0], vouch=(evidence(0, word),)))
        assert v.unvouched == 1 and v.vouched == 0 and why in v.why, v.why
        assert not v.batch.intervened.any()


def test_a_signed_word_already_used_by_another_actor_makes_a_one_ulp_copy_a_replay(run):
    vouching, guard = _vouching(run), ReplayGuard()
    e = evidence(0, _word(run))
    a0 = _batch(iv=[1, 0, 0, 0], vouch=(e,))
    v = vouching.judge(a0)
    assert v.vouched == 1
    vouching.stored(v, "a0")
    guard.stored(batch_digest(a0), "a0")
    ulp = a0.obs.copy()
    ulp[0, 0] = np.nextafter(ulp[0, 0], np.float32(2))
    copy = _batch(actor="f1", iv=[1, 0, 0, 0], vouch=(e,)).replace(obs=ulp, next_obs=a0.next_obs)
    assert guard.check(copy, False)[1] is None  # (the digest alone: the one-ulp change makes it new)
    v2 = vouching.judge(copy)
    assert v2.replay_of == "a0" and "signed for actor a0" in v2.why


def test_a_signed_word_vouches_for_at_most_rows_per_word_rows(run):
    vouching, word = _vouching(run), _word(run)
    n = ROWS_PER_WORD + 8
    v = vouching.judge(_batch(n=n, vouch=tuple(evidence(i, word) for i in range(n))))
    assert v.vouched == ROWS_PER_WORD and v.unvouched == 8 and "more than" in v.why
    vouching.stored(v, "a0")
    assert vouching.judge(_batch(n=2, first=n, vouch=(evidence(0, word),))).vouched == 0


def test_demonstrations_are_prior_data_only_from_a0_and_only_its_first_rows(run):
    vouching = _vouching(run, demo_limit=6)
    demo = ((0,), (1,), (2,), (3,))
    assert vouching.judge(_batch(vouch=demo)).demo == 4
    late = vouching.judge(_batch(first=4, vouch=demo))  # running indices 4..7: 4 and 5 are demonstrations
    assert (late.demo, late.unvouched) == (2, 2) and "demonstrations end before 6" in late.why
    other = vouching.judge(_batch(actor="f1", vouch=demo))
    assert other.vouched == 0 and "only a0 replays them" in other.why


def test_the_demonstration_window_covers_the_tasks_and_the_teachers_demonstrations():
    """--recipe hil-serl's teacher records its demonstrations as a0's first rows: without them in the window its
    kept episodes were stored as ordinary data (found merging the recipe with vouching)."""
    from types import SimpleNamespace

    from khgrl.common.delivery.vouching import demo_rows

    task = SimpleNamespace(demos=np.zeros((3, 50, 2)), horizon=100)
    assert demo_rows(task) == 300 and demo_rows(task, teacher_demos=20) == 2300
    assert demo_rows(SimpleNamespace(demos=np.zeros(0), horizon=100), teacher_demos=2) == 200


def test_the_replay_guard_ignores_the_flag_and_exempts_only_vouched_batches():
    guard = ReplayGuard()
    policy = _batch(iv=[0, 0, 0, 0])
    guard.stored(batch_digest(policy), "a0")
    flipped = _batch(actor="f1", iv=[1, 1, 1, 1])  # the same content flagged human-driven
    assert batch_digest(flipped) == batch_digest(policy)
    assert guard.check(flipped, vouched=False)[1] == "a0"  # (before: exempt, stored as prior data)
    assert guard.check(flipped, vouched=True)[1] is None
    assert guard.check(flipped)[1] is None  # (a run without role keys: the flag, as before)


# ------------------------------------------------------------------------------------ the learner end to end
def _loop(tmp_path, run):
    tqc = TQCSettings(learning_starts=10_000, buffer_size=1000, net_arch=(8, 8), batch_size=8)
    trainer, streams = open_learner(tqc, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))

    class Pub:
        queries = 0

        def ack(self, msg: Ack) -> None:
            pass

        weights = status = ack

    keys = DataKeys(run=None, kid="learner:learner", public=PublicKeys(run))
    return LearnerLoop(trainer, streams, Pub(), learner_id="learner", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag(), lead_cap=None, key=keys), trainer


def test_the_learner_stores_forged_flags_as_ordinary_data_and_refuses_replayed_words(tmp_path, run):
    loop, trainer = _loop(tmp_path, run)
    word = _word(run)
    a0 = _batch(n=8, iv=[1] * 8, vouch=tuple(evidence(i, word) for i in range(8)))
    assert loop.offer(a0) == "accepted"
    forged = _batch(n=8, actor="f1", iv=[1] * 8, seed=5)  # f1 flags its own rows human-driven
    assert loop.offer(forged) == "accepted"
    ulp = a0.reward + np.float32(2 ** -23)
    copy = _batch(n=8, actor="f1", seq=1, first=8, vouch=a0.vouch).replace(obs=a0.obs, next_obs=a0.next_obs,
                                                                          action=a0.action, reward=ulp)
    assert loop.offer(copy) == "accepted"  # (its stream moves on) but not stored
    rb, ing = trainer.buffer, loop.ingest
    assert rb.prior_slots() == 8 and trainer.total == 16  # a0's 8 vouched rows; f1's 8 as ordinary data
    assert ing.results["unvouched"] == 8 and ing.results["replayed"] == 1
    assert ing.rejects.by_kind()["unvouched"] == 1 and ing.vouching.counts["vouched"] == 8


def test_the_learner_takes_demonstrations_from_the_actor_that_replays_them():
    from khgrl.actor import demos
    from khgrl.common.delivery import vouching

    assert vouching.FIRST_ACTOR == demos.FIRST_ACTOR


def test_khgrl_bench_vouch_runs_and_vouches_for_every_row(tmp_path):
    from khgrl.benchmarks.vouch import run_vouch_benchmark

    res = run_vouch_benchmark(rows=4, repeats=1, out=str(tmp_path / "v.json"))
    assert res["vouched"] == 4 and 60 < res["wire_bytes_per_row"] < 130 and (tmp_path / "v.json").is_file()
