"""Learner and actor processes end to end over a real Zenoh router (each a separate OS process).

Small and fast on purpose: low_cov scenario, 2 episodes per actor (~250 steps each with a random policy),
``--learning-starts 16``. Only the first test runs at ``--max-lead 8`` (the single-process SB3 schedule,
one ~0.4 s training iteration per 8 steps on a 2-core box, so with a longer random warm-up); the others let
the actor run ahead. Most of the time is process start-up (imports + fitting the world: 10-20 s per actor).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import ProcGroup, read_json, unique_run, wait_for

FAST = ["--scenario", "low_cov", "--method", "khgrl", "--learning-starts", "16"]
TRAIN_FREQ = 8
LOCKSTEP_STARTS = 384  # random warm-up; ~15 lock-step iterations follow in 2 episodes


def checkpoint(run_dir: Path) -> tuple[dict, dict[str, np.ndarray]]:
    from learner.service import load_checkpoint_arrays

    ck = run_dir / "learner" / "checkpoint"
    return read_json(ck / "state.json"), load_checkpoint_arrays(ck)


def provenance(state: dict, arrays: dict) -> dict[str, list[int]]:
    """Per actor id: the per-actor indices of the transitions in the replay buffer (sorted)."""
    pos = state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]
    codes = arrays["provenance_actor"][:pos]
    steps = arrays["provenance_step"][:pos]
    assert np.all(codes >= 0), "an empty slot inside the filled part of the replay buffer"
    out: dict[str, list[int]] = {}
    for code, entry in enumerate(state["codes"]):
        out.setdefault(entry["actor"], []).extend(steps[codes == code].tolist())
    return {a: sorted(v) for a, v in out.items()}


def assert_exactly_once(state: dict, arrays: dict, actor: str, n: int) -> None:
    got = provenance(state, arrays)[actor]
    assert len(got) == n, f"{actor}: {len(got)} transitions in the buffer, the actor made {n}"
    assert got == list(range(n)), f"{actor}: provenance is not 0..{n - 1} exactly once"


# ------------------------------------------------------------------------------ unit level (no Zenoh)
def test_protocol_fields_added_for_learner_and_actor():
    from common.protocol import ProtocolError, decode, encode

    ack = dict(actor="a0", received=3, durable=1, trained=24, epoch="e1", version=2)
    assert decode("ack", encode("ack", "learner", 0, **ack))["version"] == 2
    assert decode("ack", encode("ack", "learner", 0, **ack, stream="s1"))["stream"] == "s1"
    with pytest.raises(ProtocolError, match="version"):
        decode("ack", encode("ack", "learner", 0, **{k: v for k, v in ack.items() if k != "version"}))
    with pytest.raises(ProtocolError, match="stream"):
        decode("ack", encode("ack", "learner", 0, **ack, stream="a/b"))
    w = dict(version=1, trained={"a0": 8}, tensors={"w": np.zeros((2, 2), np.float32)})
    assert decode("weights", encode("weights", "learner", 0, **w, epoch="e1"))["epoch"] == "e1"
    with pytest.raises(ProtocolError, match="epoch"):
        decode("weights", encode("weights", "learner", 0, **w, epoch=5))
    n = 2
    tr = dict(actor="a0", first_step=0, obs=np.zeros((n, 5), np.float32), next_obs=np.zeros((n, 5), np.float32),
              action=np.zeros((n, 2), np.float32), reward=np.zeros(n, np.float32),
              **{f: np.zeros(n, np.uint8) for f in ("terminated", "truncated", "intervened", "clipped")})
    assert decode("transitions", encode("transitions", "a0", 5, **tr, base_seq=3, stream="s1"))["base_seq"] == 3
    with pytest.raises(ProtocolError, match="base_seq"):
        decode("transitions", encode("transitions", "a0", 5, **tr, base_seq=6))


def test_outbox_spills_and_drops(tmp_path):
    from actor.service import Outbox

    box = Outbox(memory=3, spill_dir=tmp_path / "outbox")
    for s in range(8):
        box.add(s, f"batch{s}".encode())
    assert len(box) == 8 and len(list((tmp_path / "outbox").iterdir())) == 5
    assert box.get(1) == b"batch1" and box.get(7) == b"batch7"
    assert box.seqs_after(4) == [5, 6, 7] and box.oldest() == 0 and box.newest() == 7
    box.drop_through(5)
    assert len(box) == 2 and box.oldest() == 6 and not list((tmp_path / "outbox").iterdir())


def test_correction_arbitration():
    from actor.service import CorrectionArbiter

    arb = CorrectionArbiter("a0", timeout=0.5, enabled=True)

    def c(client, active, p=(0.5, 0.5), actor="a0", episode=1):
        m = {"client": client, "actor": actor, "active": active, "episode": episode}
        if active:
            m["p_h"] = np.array(p)
        return m

    arb.offer(c("h1", True, (0.4, 0.6)), arrival=10.0, episode=1)
    arb.offer(c("h2", True, (0.9, 0.9)), arrival=10.1, episode=1)  # someone else: ignored
    arb.offer(c("h1", True, actor="a1"), arrival=10.1, episode=1)  # another actor's
    assert np.allclose(arb.current(10.2), [0.4, 0.6]) and arb.counts["ignored_other_client"] == 1
    assert arb.counts["ignored_other_actor"] == 1
    arb.extend(1.0)  # the actor paused for 1 s: the holder's silence does not count
    assert arb.current(11.3) is not None
    assert arb.current(11.7) is None and arb.counts["timeouts"] == 1  # silent > 0.5 s of running time
    arb.offer(c("h2", True, (0.9, 0.9)), arrival=12.0, episode=1)  # free again: h2 takes over
    arb.offer(c("h2", True, episode=0), arrival=12.1, episode=1)  # a frame of an old episode: stale
    assert np.allclose(arb.current(12.2), [0.9, 0.9]) and arb.counts["stale_episode"] == 1
    arb.offer(c("h2", False), arrival=12.3, episode=1)
    assert arb.current(12.3) is None
    kgrl = CorrectionArbiter("a0", timeout=0.5, enabled=False)
    kgrl.offer(c("h1", True), arrival=0.0, episode=1)
    assert kgrl.current(0.1) is None and kgrl.counts["ignored_method"] == 1


def test_correction_arbitration_step_addressed():
    """A step-addressed client puts the actor in lock-step for the episode: each step waits for its word."""
    from actor.service import CorrectionArbiter

    arb = CorrectionArbiter("a0", timeout=0.5, enabled=True)

    def c(client, step, p=None, episode=1):
        m = {"client": client, "actor": "a0", "active": p is not None, "episode": episode, "step": step}
        if p is not None:
            m["p_h"] = np.array(p)
        return m

    assert arb.ready(5)  # nobody in lock-step: never wait
    arb.offer(c("s", 6, (0.1, 0.2)), arrival=1.0, episode=1, step=5)  # early: kept for step 6
    assert arb.lockstep == "s" and not arb.ready(5) and arb.ready(6)
    arb.offer(c("s", 5), arrival=1.0, episode=1, step=5)  # release word for step 5
    assert arb.ready(5) and arb.current(1.0, 5) is None
    assert np.allclose(arb.current(1.1, 6), [0.1, 0.2]) and arb.holder == "s"
    assert not arb.ready(7)  # waits for step 7's word...
    arb.offer(c("s", 6, (0.9, 0.9)), arrival=1.2, episode=1, step=7)  # ...one for a step already taken is late
    arb.offer(c("g", 7, (0.5, 0.5)), arrival=1.2, episode=1, step=7)  # another client: ignored
    arb.offer(c("s", 7, (0.3, 0.3), episode=2), arrival=1.2, episode=1, step=7)  # another episode: stale
    assert arb.counts["late_step"] == 1 and arb.counts["ignored_other_client"] == 1 and arb.counts["stale_episode"] == 1
    assert not arb.ready(7)
    arb.offer(c("s", 7, (0.3, 0.4)), arrival=1.3, episode=1, step=7)
    assert np.allclose(arb.current(5.0, 7), [0.3, 0.4])  # applied at its step, whatever the wall time
    arb.give_up(8)  # silent at step 8: plain mode again, the last P_h holds until the timeout
    assert arb.ready(8) and arb.counts["lockstep_timeouts"] == 1
    assert np.allclose(arb.current(5.1, 8), [0.3, 0.4]) and arb.current(5.6, 9) is None
    arb.offer(c("s", 3, (0.2, 0.2), episode=2), arrival=6.0, episode=2, step=3)
    assert np.allclose(arb.current(6.0, 3), [0.2, 0.2])
    arb.offer(c("s", 0, (0.6, 0.6), episode=3), arrival=6.0, episode=2, step=4)  # announces episode 3
    arb.new_episode(3)  # a lock-step hold ends with its episode; the announced client is in lock-step at once
    assert arb.holder is None and arb.lockstep == "s" and arb.ready(0) and not arb.ready(1)
    assert np.allclose(arb.current(6.1, 0), [0.6, 0.6])
    arb.offer(c("s", 1, episode=3), arrival=6.2, episode=3, step=1)
    assert arb.current(6.2, 1) is None and arb.counts["releases"] == 2  # the old hold at new_episode, this word
    arb.new_episode(4)  # no announcement: plain mode
    assert arb.lockstep is None and arb.ready(0)


def test_learner_core_orders_stream_and_keeps_sb3_schedule(tmp_path):
    from common.protocol import decode, encode
    from learner.service import LearnerCore

    core = LearnerCore(tmp_path, learning_starts=16, buffer_size=1000, logger_formats=("csv",))
    rng = np.random.default_rng(0)

    def batch(seq, first, n, actor="a0", base=0):
        obs = rng.uniform(0, 1, (n, 5)).astype(np.float32)
        f = dict(actor=actor, first_step=first, obs=obs, next_obs=obs, action=np.zeros((n, 2), np.float32),
                 reward=np.ones(n, np.float32), terminated=np.zeros(n, np.uint8), truncated=np.zeros(n, np.uint8),
                 intervened=np.ones(n, np.uint8), clipped=np.zeros(n, np.uint8), base_seq=base, stream="s0")
        return decode("transitions", encode("transitions", actor, seq, **f))

    assert core.offer(batch(1, 8, 8)) == "held"  # gap: held until seq 0 arrives
    assert core.total == 0 and core.ack_fields("a0")["received"] == -1
    assert core.offer(batch(0, 0, 8)) == "accepted"
    assert core.total == 16 and core.ack_fields("a0")["received"] == 1
    assert core.offer(batch(0, 0, 8)) == "duplicate" and core.total == 16
    # inside learning_starts: no training due, trained = everything ingested
    assert not core.due and core.ack_fields("a0")["trained"] == 16
    assert core.offer(batch(2, 16, 5)) == "accepted" and not core.due  # 21: next multiple of 8 is 24
    assert core.ack_fields("a0")["trained"] == 0  # training started, initial weights cover nothing
    assert core.offer(batch(3, 21, 8)) == "accepted"  # 29 ingested: due at 24
    assert [at for at, _ in core.due] == [24]
    assert core.train_one() and not core.train_one()
    assert core.version == 1 and core.gradient_steps == 8
    assert core.ack_fields("a0")["trained"] == 24 and core.weights_fields()["trained"] == {"a0": 24}
    assert core.iterations == 1 and int(core.flag_intervened[:29].sum()) == 29
    core.save_checkpoint()
    again = LearnerCore(tmp_path, learning_starts=16, resume=True, logger_formats=("csv",))
    assert again.total == 29 and again.version == 1 and again.streams["a0"].next_seq == 4
    assert again.ack_fields("a0")["durable"] == 3 and again.model.replay_buffer.pos == 29
    assert list(again.prov_step[:29]) == list(range(29))
    # an actor that only holds batches from seq 6 on (a fresh learner): the stream starts there
    assert again.offer(batch(6, 40, 8, actor="a1", base=6)) == "accepted"
    assert again.streams["a1"].next_seq == 7


# --------------------------------------------------------------------------- processes over Zenoh
@pytest.mark.integration
@pytest.mark.timeout(300)
def test_actor_and_learner_end_to_end(tmp_path):
    run, run_dir = unique_run(), tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        # lock-step with the learner: ~0.5 s of training per 8 steps here, so a longer random warm-up
        learner = g.learner(run, ep, "--learning-starts", str(LOCKSTEP_STARTS), "--checkpoint-every", "0")
        actor = g.actor(run, ep, *FAST, "--episodes", "2", "--max-lead", "8", "--learning-starts", str(LOCKSTEP_STARTS))
        rc = actor.wait(150)
        assert rc == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n = summary["transitions"]
    assert summary["episodes"] == 2 and summary["unconfirmed_transitions"] == 0 and summary["durable"] == summary["last_seq"]
    # --max-lead 8: every policy step used the weights single-process SB3 would have used (lag 0..7)
    assert summary["weights"]["final_version"] > 0
    assert 0 <= summary["weights"]["max_lag"] <= TRAIN_FREQ - 1, summary["weights"]
    assert summary["rate_limit"]["waits"] > 0
    episodes = json.loads((run_dir / "actor-a0" / "episodes.json").read_text())
    assert [e["episode"] for e in episodes] == [1, 2] and sum(e["steps"] for e in episodes) == n
    assert (run_dir / "actor-a0" / "episodes.csv").exists() and (run_dir / "actor-a0" / "config.json").exists()

    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)
    assert state["version"] > 0 and state["total_ingested"] == n
    # update-to-data ratio of SB3 learn(): one iteration per multiple of 8 in (learning_starts, n]
    due = len(range(TRAIN_FREQ * (LOCKSTEP_STARTS // TRAIN_FREQ + 1), n + 1, TRAIN_FREQ))
    assert state["iterations"] + len(state["due"]) == due
    assert state["gradient_steps"] == TRAIN_FREQ * state["iterations"]
    assert int(arrays["intervened"].sum()) == 0  # no human in this run
    assert list((run_dir / "learner" / "tb").glob("events.out.tfevents.*"))
    assert (run_dir / "learner" / "learner.log").exists()


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_learner_killed_and_resumed_loses_and_duplicates_nothing(tmp_path):
    run, run_dir = unique_run(), tmp_path / "run"
    state_file = run_dir / "learner" / "checkpoint" / "state.json"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "64")
        actor = g.actor(run, ep, *FAST, "--episodes", "2", "--max-lead", "100000", "--rate", "120")
        # kill after the learner has acked and checkpointed some of the stream
        wait_for(lambda: read_json(state_file)["total_ingested"] >= 128, 120, "a first checkpoint", procs=[learner, actor])
        learner.kill()
        killed_at = read_json(state_file)["total_ingested"]
        time.sleep(0.5)
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "64", "--resume")
        rc = actor.wait(150)
        assert rc == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n = summary["transitions"]
    assert summary["episodes"] == 2 and summary["unconfirmed_transitions"] == 0
    assert summary["resends"] >= 1 and n > killed_at
    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)
    assert state["total_ingested"] == n


@pytest.fixture(scope="module")
def two_actors(tmp_path_factory):
    """a0 starts with the learner; a1 joins once the learner has published trained weights."""
    base = tmp_path_factory.mktemp("two_actors")
    run, run_dir = unique_run(), base / "run"
    progress = run_dir / "learner" / "tb" / "progress.csv"
    with ProcGroup(base) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0")
        a0 = g.actor(run, ep, *FAST, "--episodes", "2", "--max-lead", "100000", "--rate", "40", "--id", "a0")
        # progress.csv gets a row per training iteration: weights version >= 1 exist
        wait_for(lambda: len(progress.read_text().splitlines()) >= 2, 120, "a first training iteration",
                 procs=[learner, a0])
        a1 = g.actor(run, ep, *FAST, "--episodes", "2", "--max-lead", "100000", "--seed", "1", "--id", "a1")
        rcs = {"a0": a0.wait(150), "a1": a1.wait(150)}
        tails = {"a0": a0.tail(), "a1": a1.tail()}
        learner_rc = learner.stop(60)
        learner_tail = learner.tail()
    return {"run_dir": run_dir, "rcs": rcs, "tails": tails, "learner_rc": learner_rc, "learner_tail": learner_tail}


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_late_joining_actor_gets_current_weights(two_actors):
    assert two_actors["rcs"]["a1"] == 0, two_actors["tails"]["a1"]
    summary = read_json(two_actors["run_dir"] / "actor-a1" / "summary.json")
    assert summary["weights"]["initial_version"] is not None and summary["weights"]["initial_version"] > 0


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_two_actors_feed_one_learner(two_actors):
    assert two_actors["rcs"] == {"a0": 0, "a1": 0}, two_actors["tails"]
    assert two_actors["learner_rc"] == 0, two_actors["learner_tail"]
    run_dir = two_actors["run_dir"]
    state, arrays = checkpoint(run_dir)
    total = 0
    for a in ("a0", "a1"):
        n = read_json(run_dir / f"actor-{a}" / "summary.json")["transitions"]
        assert_exactly_once(state, arrays, a, n)
        total += n
    assert state["total_ingested"] == total


def test_set_realtime_is_reported_truthfully():
    """The control loop's SCHED_FIFO request either takes effect (root) or is refused and says so."""
    import os
    import threading

    from actor.service import set_realtime

    out = {}

    def loop_thread():
        before = os.sched_getscheduler(0)
        out["ok"] = set_realtime(7)
        out["policy"], out["prio"] = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
        out["before"] = before

    t = threading.Thread(target=loop_thread)
    t.start()
    t.join()
    if out["ok"]:
        assert out["policy"] == os.SCHED_FIFO and out["prio"] == 7
    else:
        assert out["policy"] == out["before"] != os.SCHED_FIFO
    assert os.sched_getscheduler(0) != os.SCHED_FIFO  # only the calling thread changed
