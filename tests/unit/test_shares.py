"""Per-actor shares on the learner's receiving side (issue 21): the replay buffer's shares (learner/replay.py), held
and deferred batches capped in bytes (common/delivery/ingest.py), the lead cap, replays under another id and the
checkpoint-request limits (common/delivery/learner_side.py, common/delivery/guards.py)."""

from __future__ import annotations

import pickle
import time

import gymnasium as gym
import numpy as np
import pytest
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery import ingest
from khgrl.common.delivery.guards import RequestLimiter, batch_digest
from khgrl.common.delivery.ingest import StreamTable, batch_bytes
from khgrl.common.process import StopFlag
from khgrl.common.wire.protocol import Ack, Control, Transitions, decode, encode
from khgrl.learner.loop import LearnerLoop, open_learner
from khgrl.learner.main import lead_cap
from khgrl.learner.replay import StreamReplayBuffer
from stable_baselines3.common.buffers import ReplayBuffer

OBS = gym.spaces.Box(-1, 1, (3,), np.float32)
ACT = gym.spaces.Box(-1, 1, (2,), np.float32)


def batch(seq: int, first: int, n: int, actor: str = "a0", stream: str = "s0", seed: int = 0) -> Transitions:
    rng = np.random.default_rng(seed + 1000 * seq + hash(actor) % 997)
    obs = rng.uniform(0, 1, (n, 5)).astype(np.float32)
    msg = Transitions(actor=actor, first_step=first, obs=obs, next_obs=obs[::-1].copy(),
                      action=rng.uniform(-1, 1, (n, 2)).astype(np.float32), reward=np.ones(n, np.float32),
                      terminated=np.zeros(n, np.uint8), truncated=np.zeros(n, np.uint8),
                      intervened=np.zeros(n, np.uint8), clipped=np.zeros(n, np.uint8), base_seq=0, stream=stream,
                      task="0123456789abcdef")
    return decode(Transitions, encode(msg, actor, seq))


def _add(rb: StreamReplayBuffer, code: int, first: int, n: int, value: float = 0.0) -> None:
    o = np.full((n, 3), value, np.float32) + np.arange(first, first + n, dtype=np.float32)[:, None]
    rb.add_batch(o, o + 1, o[:, :2], o[:, 0], np.zeros(n), np.zeros(n), intervened=np.zeros(n, np.uint8),
                 clipped=np.zeros(n, np.uint8), actor=code, first_step=first)


def _held(rb: StreamReplayBuffer) -> dict[int, int]:
    codes, counts = np.unique(rb.provenance_actor, return_counts=True)
    return dict(zip(codes.tolist(), counts.tolist()))


# ------------------------------------------------------------------------------------ the replay buffer's shares
def test_one_actor_fills_and_overwrites_exactly_as_sb3_first_in_first_out():
    rb = StreamReplayBuffer(50, OBS, ACT, handle_timeout_termination=True)
    ref = ReplayBuffer(50, OBS, ACT, handle_timeout_termination=True)
    rng, step = np.random.default_rng(0), 0
    for b in range(80):
        n = int(rng.integers(1, 13))
        _add(rb, 0, step, n)
        o = np.zeros((n, 3), np.float32) + np.arange(step, step + n, dtype=np.float32)[:, None]
        for j in range(n):
            ref.add(o[j:j + 1], o[j:j + 1] + 1, o[j:j + 1, :2], o[j:j + 1, 0], np.zeros(1),
                    [{"TimeLimit.truncated": False}])
        step += n
        if b == 40:  # a checkpoint and a resume in between: the slot queues are rebuilt from the provenance
            rb = pickle.loads(pickle.dumps(rb))
        assert np.array_equal(rb.observations, ref.observations) and (rb.pos, rb.full) == (ref.pos, ref.full)
    assert np.array_equal(rb.provenance_step, rb.observations[:, 0, 0].astype(np.int64))


def test_a_flooding_actor_cannot_evict_another_below_its_share():
    rb = StreamReplayBuffer(100, OBS, ACT)
    rb.stream_codes = [{"actor": "a0", "stream": "x"}, {"actor": "f", "stream": "y"}, {"actor": "f", "stream": "z"}]
    _add(rb, 0, 0, 30)  # a0: 30 slots
    for i in range(40):  # f sends 40 x 50 transitions, half of them from a second stream of its id
        _add(rb, 1 + i % 2, 50 * i, 50, value=1000.0)
    held = _held(rb)
    assert held[0] == 30 and held[1] + held[2] == 70  # a0 is under its share (50): nothing of it was evicted
    assert rb.shares() == {"a0": 30, "f": 70}
    _add(rb, 0, 30, 40)  # a0 grows to its share, taking f's oldest slots
    assert rb.shares() == {"a0": 50, "f": 50}
    kept = rb.observations[rb.provenance_actor == 0, 0, 0]
    assert sorted(kept.tolist()) == list(range(20, 70))  # a0 over its share: its own oldest went first
    f_steps = np.sort(rb.provenance_step[rb.provenance_actor >= 1])
    assert f_steps[0] >= 35 * 50  # what f kept is its newest


def test_a_new_actor_takes_its_share_from_the_actor_most_over_it():
    rb = StreamReplayBuffer(90, OBS, ACT)
    rb.stream_codes = [{"actor": a, "stream": a} for a in ("a0", "a1", "a2")]
    _add(rb, 0, 0, 60)
    _add(rb, 1, 0, 30)
    _add(rb, 2, 0, 45)  # share 30 each: a2 takes from a0 (60 -> 30)
    assert rb.shares() == {"a0": 30, "a1": 30, "a2": 30}
    assert sorted(rb.provenance_step[rb.provenance_actor == 0].tolist()) == list(range(30, 60))


def test_an_old_checkpoint_buffer_loads_and_gets_shares(tmp_path):
    rb = StreamReplayBuffer(20, OBS, ACT)
    _add(rb, 0, 0, 25)
    state = rb.__getstate__()
    for name in ("stream_codes", "_queues", "sample_limit"):
        state.pop(name, None)  # what a checkpoint written before shares holds
    old = StreamReplayBuffer.__new__(StreamReplayBuffer)
    old.__setstate__(state)
    old.stream_codes = [{"actor": "a0", "stream": "s"}, {"actor": "a1", "stream": "t"}]
    _add(old, 1, 0, 15)
    assert old.shares() == {"a0": 10, "a1": 10}


# ------------------------------------------------------------------------------------ held batches: bytes
def test_held_batches_are_capped_in_bytes_per_actor_and_in_all(monkeypatch):
    big = batch(1, 512, 512)
    size = batch_bytes(big)
    monkeypatch.setattr(ingest, "PENDING_BYTES_PER_ACTOR", 3 * size)
    monkeypatch.setattr(ingest, "PENDING_BYTES_TOTAL", 5 * size)
    table = StreamTable()
    results = [table.offer(batch(s, 512 * s, 512)).result for s in range(1, 6)]
    assert results == ["held"] * 3 + ["dropped"] * 2 and table.pending_bytes == 3 * size
    results = [table.offer(batch(s, 512 * s, 512, actor="b")).result for s in range(1, 4)]
    assert results == ["held", "held", "dropped"] and table.pending_bytes == 5 * size
    assert table.dropped_pending == 3
    res = table.offer(batch(0, 0, 512))  # the gap is filled: what was held goes, its bytes are freed
    assert [m.envelope.seq for m in res.ready] == [0, 1, 2, 3] and table.pending_bytes == 2 * size
    assert table.offer(batch(4, 2048, 512)).result == "accepted"


# ------------------------------------------------------------------------------------ the lead cap
def _loop(tmp_path, cap: int | None, learning_starts: int = 16):
    tqc = TQCSettings(learning_starts=learning_starts, buffer_size=1000, net_arch=(8, 8), batch_size=8)
    trainer, streams = open_learner(tqc, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))

    class Pub:
        queries = 0

        def __init__(self) -> None:
            self.acks: list[Ack] = []

        def ack(self, msg: Ack) -> None:
            self.acks.append(msg)

        def weights(self, msg) -> None:
            pass

        status = weights

    loop = LearnerLoop(trainer, streams, Pub(), learner_id="learner", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag(), lead_cap=cap)
    return loop, trainer


def test_an_actor_ahead_of_training_is_deferred_and_released_as_training_catches_up(tmp_path):
    cap = lead_cap(type("S", (), {"max_lead": 8, "batch": 8})())
    loop, trainer = _loop(tmp_path, cap)
    assert cap == 24
    # the flood: batches of 4,096 never fit; batches of 8 beyond the cap wait
    assert loop.offer(batch(0, 0, 4096, actor="f")) == "over_lead" and trainer.total == 0
    results = [loop.offer(batch(s, 8 * s, 8)) for s in range(12)]
    assert results[:2] == ["accepted"] * 2  # inside learning_starts (16): what is stored counts as trained
    assert results[2:5] == ["accepted"] * 3 and results[5:] == ["deferred"] + ["held"] * 6  # (behind the deferred)
    assert trainer.total == 40 and len(trainer.due) == 3  # at most cap / train_freq iterations of this actor due
    stored = [trainer.total]
    while loop.trainer.due:
        loop.step()  # train one; ack_all releases what now fits
        stored.append(trainer.total)
    assert trainer.total == 96 and loop.ingest.streams["a0"].next_seq == 12 and not loop.ingest.streams["a0"].pending
    assert all(b - a <= 8 for a, b in zip(stored, stored[1:]))  # one batch per iteration, as the schedule allows
    assert loop.ingest.rejects.by_kind()["over_lead"] == 1


def test_without_a_cap_robot_mode_and_unit_loops_store_everything(tmp_path):
    loop, trainer = _loop(tmp_path, None)
    assert [loop.offer(batch(s, 8 * s, 8)) for s in range(12)] == ["accepted"] * 12 and trainer.total == 96


def test_a_lock_step_actor_is_never_deferred(tmp_path):
    loop, trainer = _loop(tmp_path, 24)
    for s in range(40):  # max_lead 8: the actor sends a batch only once the previous one is trained on
        assert loop.offer(batch(s, 8 * s, 8)) == "accepted"
        loop.step()
    assert trainer.total == 320 and loop.ingest.results["deferred"] == 0


def test_a_rewinding_actor_cannot_make_its_stored_transitions_look_trained(tmp_path):
    loop, trainer = _loop(tmp_path, 24, learning_starts=0)
    results = [loop.offer(batch(s, 0, 8, actor="f")) for s in range(10)]  # every batch claims steps 0..7
    assert results.count("accepted") <= 3 and trainer.total <= 24


# ------------------------------------------------------------------------------------ replays under another id
def test_a_batch_replayed_under_another_id_is_not_stored_again(tmp_path):
    loop, trainer = _loop(tmp_path, None)
    originals = [batch(s, 8 * s, 8) for s in range(4)]
    for m in originals:
        loop.offer(m)
    for s, m in enumerate(originals):  # the attacker republishes a0's batches under its own id and seq
        copy = m.replace(actor="f", stream="fs", envelope=None)
        assert loop.offer(decode(Transitions, encode(copy, "f", s))) == "accepted"
    assert trainer.total == 32 and loop.ingest.rejects.by_kind()["replayed"] == 4
    f = loop.ingest.streams["f"]
    assert f.next_seq == 4 and f.ingested == 0 and not loop.ingest.admitted("f")  # moved on, nothing stored
    assert loop.offer(batch(4, 32, 8, actor="f", stream="fs")) == "accepted" and trainer.total == 40  # its own data
    # the same actor id may send the same content again (a restarted actor's fresh stream repeats its warm-up)
    again = originals[0].replace(stream="s1", envelope=None)
    assert loop.offer(decode(Transitions, encode(again, "a0", 0))) == "accepted" and trainer.total == 48


def test_identical_human_driven_batches_of_two_actors_are_both_stored(tmp_path):
    """A scripted human in a deterministic world drives two actors through the same steps: their batches are
    byte-identical and both honest. Only a batch with a step of the policy can be a replay."""
    loop, trainer = _loop(tmp_path, None)
    human = batch(0, 0, 8).replace(intervened=np.ones(8, np.uint8), envelope=None)
    for actor in ("a0", "a1"):
        twin = human.replace(actor=actor, stream="s0" if actor == "a0" else "s-a1")
        assert loop.offer(decode(Transitions, encode(twin, actor, 0))) == "accepted"
    assert trainer.total == 16 and "replayed" not in loop.ingest.rejects.by_kind()
    policy = batch(1, 8, 8)  # (intervened all 0) from a0, then the same content from a1: a replay
    assert loop.offer(policy) == "accepted"
    copy = policy.replace(actor="a1", stream="s-a1", envelope=None)
    assert loop.offer(decode(Transitions, encode(copy, "a1", 1))) == "accepted"
    assert trainer.total == 24 and loop.ingest.rejects.by_kind()["replayed"] == 1


def test_batch_digest_costs_little_per_4_mib_batch():
    n = 4096
    obs = np.random.default_rng(0).random((n, 128), dtype=np.float32)
    msg = batch(0, 0, 1).replace(obs=obs, next_obs=obs.copy(), action=np.zeros((n, 2), np.float32),
                                 reward=np.zeros(n, np.float32), terminated=np.zeros(n, np.uint8),
                                 truncated=np.zeros(n, np.uint8), intervened=np.zeros(n, np.uint8),
                                 clipped=np.zeros(n, np.uint8))
    assert batch_bytes(msg) > 4 * 2**20 * 0.95
    t0 = time.perf_counter()
    for _ in range(20):
        batch_digest(msg)
    per = (time.perf_counter() - t0) / 20
    print(f"blake2b digest of a {batch_bytes(msg) / 2**20:.2f} MiB batch: {per * 1e3:.2f} ms")
    assert per < 0.1  # (measured 6-7 ms on this 2-core machine under load)


# ------------------------------------------------------------------------------------ checkpoint requests
def test_checkpoint_requests_only_from_admitted_actors_and_rate_limited():
    now = [0.0]
    admitted = {"a0", "a1"}
    lim = RequestLimiter(admitted.__contains__, every_s=2.0, gap_s=1.0, clock=lambda: now[0])
    assert "not stored" in lim.refuse("x")
    assert lim.refuse("a0") is None and lim.due() and not lim.due()
    assert "more than one" in lim.refuse("a0")
    now[0] = 0.5
    assert lim.refuse("a1") is None and not lim.due()  # within the gap: waits, is not lost
    now[0] = 1.0
    assert lim.due()
    now[0] = 2.5
    assert lim.refuse("a0") is None and lim.due()


def test_loop_honours_requests_of_admitted_streams_only(tmp_path):
    loop, trainer = _loop(tmp_path, None)
    ingest_ = loop.ingest
    key = "khgrl/unit/actor/{}/request"
    payload = lambda a: encode(Control(command="checkpoint"), a, 0)  # noqa: E731
    for _ in range(50):
        ingest_.receive("request", key.format("x"), payload("x"))
    assert not loop.checkpoint_requested and ingest_.rejects.by_kind()["control"] == 50
    loop.offer(batch(0, 0, 8))
    for _ in range(50):
        ingest_.receive("request", key.format("a0"), payload("a0"))
    assert loop.checkpoint_requested and ingest_.rejects.by_kind()["control"] == 99


@pytest.mark.parametrize("n", [1, 8])
def test_batch_bytes_counts_every_array(n):
    m = batch(0, 0, n)
    assert batch_bytes(m) == n * (5 * 4 * 2 + 2 * 4 + 4 + 4)


def test_honest_actors_in_flow_control_are_never_deferred(tmp_path):
    """Three actors, each sending a batch of 8 whenever (sent - its last ack's trained) < max_lead 8, batches cut
    off the global training grid (an end-of-episode batch of 3 now and then): the learner never defers one."""
    loop, trainer = _loop(tmp_path, 24)
    pub = loop.pub
    sent = {a: 0 for a in ("a0", "a1", "a2")}
    seq = {a: 0 for a in sent}

    def trained(a: str) -> int:
        acks = [m for m in pub.acks if m.actor == a]
        return acks[-1].trained if acks else 0

    for rnd in range(60):
        for a in sent:
            if sent[a] - trained(a) < 8:
                n = 3 if (rnd + seq[a]) % 7 == 0 else 8
                assert loop.offer(batch(seq[a], sent[a], n, actor=a, stream=a)) == "accepted", (rnd, a)
                loop.ingest.ack_touched()
                sent[a] += n
                seq[a] += 1
        loop.step()
    assert loop.ingest.results["deferred"] == 0 and trainer.total == sum(sent.values()) > 400
