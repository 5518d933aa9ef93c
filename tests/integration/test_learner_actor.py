"""Learner and actor processes end to end over a real Zenoh router (each a separate OS process).

Small and fast on purpose: low_cov scenario, 2 episodes per actor (~250 steps each with a random policy),
``--learning-starts 16``. Only the first test runs at ``--max-lead 8`` (the single-process SB3 schedule,
one ~0.4 s training iteration per 8 steps on a 2-core box, so with a longer random warm-up); the others let
the actor run ahead. Most of the time is process start-up (imports + fitting the world: 10-20 s per actor).
Also here: a forged ack cannot make the actor drop batches the learner does not hold, and ``--resume`` of an
actor continues its episode numbering and appends to its files. (The actor's parts without Zenoh:
tests/unit/test_actor_parts.py.)
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import SMALL_GRADIENT_STEPS, ProcGroup, read_json, unique_run, wait_for

FAST = ["--scenario", "low_cov", "--method", "khgrl", "--learning-starts", "16"]
TRAIN_FREQ = 8
LOCKSTEP_STARTS = 384  # random warm-up; ~15 lock-step iterations follow in 2 episodes


def checkpoint(run_dir: Path) -> tuple[dict, dict[str, np.ndarray]]:
    from khgrl.learner.checkpoint import load_checkpoint_arrays

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
    assert summary["episodes"] == 2 and summary["unconfirmed_transitions"] == 0
    assert summary["durable"] == summary["last_seq"]
    # --max-lead 8: every policy step used the weights single-process SB3 would have used (lag 0..7)
    assert summary["weights"]["final_version"] > 0
    assert 0 <= summary["weights"]["max_lag"] <= TRAIN_FREQ - 1, summary["weights"]
    assert summary["rate_limit"]["waits"] > 0
    episodes = json.loads((run_dir / "actor-a0" / "episodes.json").read_text())
    assert [e["episode"] for e in episodes] == [1, 2] and sum(e["steps"] for e in episodes) == n
    assert (run_dir / "actor-a0" / "episodes.csv").exists()
    config = read_json(run_dir / "actor-a0" / "config.json")  # the resolved run configuration + the actor's facts
    assert config["tqc"]["learning_starts"] == LOCKSTEP_STARTS and config["stream"]["max_lead"] == 8
    assert config["runtime"]["actor_id"] == "a0" and config["runtime"]["stream"] == summary["stream"]
    assert config["runtime"]["resumed"] is False and summary["refused_acks"] == 0

    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)
    assert state["version"] > 0 and state["total_ingested"] == n
    # update-to-data ratio of SB3 learn(): one iteration per multiple of 8 in (learning_starts, n]
    due = len(range(TRAIN_FREQ * (LOCKSTEP_STARTS // TRAIN_FREQ + 1), n + 1, TRAIN_FREQ))
    assert state["iterations"] + len(state["due"]) == due
    assert state["gradient_steps"] == SMALL_GRADIENT_STEPS * state["iterations"]
    assert int(arrays["intervened"].sum()) == 0  # no human in this run
    assert list((run_dir / "learner" / "tb").glob("events.out.tfevents.*"))
    assert (run_dir / "learner" / "learner.log").exists()


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_learner_killed_and_resumed_loses_and_duplicates_nothing(tmp_path):
    """SIGKILL after the learner acked batches durable from its journal alone (no full checkpoint yet: the
    default settings write one only at the end, or once the journal holds a replay buffer's worth); the actor
    dropped those batches from its outbox, so only the journal's replay can bring them back."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys, Status, decode

    run, run_dir = unique_run(), tmp_path / "run"
    latest: list = [None]
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16", "--model-checkpoint-every", "4")
        actor = g.actor(run, ep, *FAST, "--episodes", "2", "--max-lead", "100000", "--rate", "120")
        with open_client(ep, timeout=60) as s:
            sub = s.declare_subscriber(Keys(run).status("learner", "*"),
                                       lambda smp: latest.__setitem__(0, decode(Status, smp.payload.to_bytes()).info))
            try:  # kill once the journal made at least 16 batches durable and no full checkpoint was written
                info = wait_for(lambda: latest[0] if latest[0] and latest[0].durable.get("a0", -1) >= 15 else None,
                                120, "batches durable in the journal", procs=[learner, actor])
            finally:
                sub.undeclare()
        assert info.checkpoints == 0 and not (run_dir / "learner" / "checkpoint").exists()
        learner.kill()
        durable_at_kill = info.durable["a0"]
        assert list((run_dir / "learner" / "journal").glob("segment-*.bin"))
        time.sleep(0.5)
        learner = g.learner(run, ep, "--learning-starts", "16", "--resume")
        rc = actor.wait(150)
        assert rc == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n = summary["transitions"]
    assert summary["episodes"] == 2 and summary["unconfirmed_transitions"] == 0
    assert summary["resends"] >= 1 and n > 8 * (durable_at_kill + 1)
    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)
    assert state["total_ingested"] == n
    # the final checkpoint holds them: the segments before it are gone, the one after it (made at the cut, so that a
    # learner resumed later numbers on from there) is empty
    left = list((run_dir / "learner" / "journal").glob("segment-*.bin"))
    assert [p.stat().st_size for p in left] == [0] and left[0].name == f"segment-{state['journal']['next']:06d}.bin"
    text = (run_dir / "learner" / "learner.log").read_text()
    assert "journal: replayed" in text and "no full checkpoint under" in text, text[-3000:]


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


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_forged_ack_cannot_make_the_actor_drop_undelivered_batches(tmp_path):
    """Someone on the router acks every batch as durable (with the real stream id and epoch); then the learner
    dies and resumes from what its journal holds, which is less. The actor refused the forged acks, so it still
    holds and re-sends everything after that: the learner ends up with every transition exactly once."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Ack, Control, Transitions
    from khgrl.common.wire.protocol import Keys, decode, encode

    run, run_dir = unique_run("forge"), tmp_path / "run"
    keys = Keys(run)
    seen: dict = {}

    def on_ack(sample) -> None:
        msg = decode(Ack, sample.payload.to_bytes())
        if msg.received < 10**6:
            seen["ack"] = msg

    def on_transitions(sample) -> None:
        seen["stream"] = decode(Transitions, sample.payload.to_bytes()).stream

    forged_sent = 5
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0")
        actor = g.actor(run, ep, *FAST, "--episodes", "2", "--max-lead", "100000", "--rate", "120")
        with open_client(ep) as s:
            subs = [s.declare_subscriber(keys.ack("a0"), on_ack),
                    s.declare_subscriber(keys.transitions("a0"), on_transitions)]
            try:
                wait_for(lambda: "stream" in seen and "ack" in seen and seen["ack"].durable >= 8, 120,
                         "the learner acking the actor's batches durable", procs=[learner, actor])
                s.put(keys.control("learner"), encode(Control(command="checkpoint"), "tester", 0))
                time.sleep(1.0)  # ~120 more transitions
                forged = Ack(actor="a0", received=10**6, durable=10**6, trained=0, version=0,
                             epoch=seen["ack"].epoch, stream=seen["stream"])
                for i in range(forged_sent):
                    s.put(keys.ack("a0"), encode(forged, "learner", 10**6 + i))
                    time.sleep(0.02)
                time.sleep(0.3)
                learner.kill()
            finally:
                for sub in subs:
                    sub.undeclare()
        at_kill = 8 * (seen["ack"].durable + 1)
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0", "--resume")
        rc = actor.wait(150)
        assert rc == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n = summary["transitions"]
    assert summary["episodes"] == 2 and summary["unconfirmed_transitions"] == 0 and n > at_kill
    assert summary["refused_acks"] == forged_sent and summary["rejects"] == {"ack": forged_sent}, summary
    assert summary["durable"] == summary["last_seq"]
    log = (run_dir / "actor-a0" / "actor.log").read_text()
    assert "ack claims batches beyond the highest seq sent" in log
    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_resumed_actor_continues_episode_numbering_and_appends(tmp_path):
    """Part 1: 2 episodes; part 2 (--resume, --episodes 3): episode 3 only, numbered 3 in its frames, rows
    appended to episodes.csv / corrections.csv, a new TensorBoard event file beside the first; part 3: nothing
    left to run. The scripted human helps in episodes 1 and 3 of the whole run."""
    import csv

    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Frame
    from khgrl.common.wire.protocol import Keys, decode

    run, run_dir = unique_run("resume"), tmp_path / "run"
    out = run_dir / "actor-a0"
    # 100 Hz: the scripted human's first word of an episode (for step 1) arrives before the actor takes step 1
    flags = [*FAST, "--learning-starts", "100000", "--flush-timeout", "0.5", "--tensorboard", "--rate", "100"]
    frames: list[Frame] = []
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        human = g.human(run, ep, "scripted", "--scenario", "low_cov", "--human-episodes", "1", "3")
        part1 = g.actor(run, ep, *flags, "--episodes", "2")
        assert part1.wait(150) == 3, part1.tail()  # no learner: only the final flush times out
        assert read_json(out / "summary.json")["episodes"] == 2
        with open_client(ep) as s:
            sub = s.declare_subscriber(Keys(run).frame("a0"),
                                       lambda smp: frames.append(decode(Frame, smp.payload.to_bytes())))
            try:
                part2 = g.actor(run, ep, *flags, "--episodes", "3", "--resume")
                assert part2.wait(150) == 3, part2.tail()
                time.sleep(0.5)
            finally:
                sub.undeclare()
        summary2 = read_json(out / "summary.json")
        part3 = g.actor(run, ep, *flags, "--episodes", "3", "--resume")
        # all 3 episodes of the run are done: nothing to run, but the batches of parts 1 and 2 that no learner
        # confirmed are still held (the stream continues): the flush times out again
        assert part3.wait(150) == 3, part3.tail()
        human.stop(30)

    assert summary2["episodes"] == 1 and summary2["first_episode"] == 3
    assert read_json(out / "summary.json")["episodes"] == 0
    assert {f.episode for f in frames} == {3}
    lasts = [f for f in frames if f.last]
    assert len(lasts) == 1 and lasts[0].t == max(f.t for f in frames), "one final frame, flagged last"
    text = (out / "episodes.csv").read_text()
    assert text.count("episode,steps") == 1
    with open(out / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["episode"] for r in rows] == ["1", "2", "3"]
    assert lasts[0].t == int(rows[2]["steps"]) - 1
    assert [e["episode"] for e in read_json(out / "episodes.json")] == [1, 2, 3]
    corrections = (out / "corrections.csv").read_text()
    assert corrections.count("run,actor,episode") == 1
    with open(out / "corrections.csv", newline="") as fh:
        helped = {r["episode"] for r in csv.DictReader(fh)}
    assert helped == {"1", "3"}, helped  # the human's schedule in episodes of the whole run
    assert int(rows[0]["intervention_steps"]) > 0 and int(rows[1]["intervention_steps"]) == 0
    assert int(rows[2]["intervention_steps"]) > 0
    assert len(list((out / "tb").glob("events.out.tfevents.*"))) >= 2
    config = read_json(out / "config.json")
    assert config["runtime"]["resumed"] is True and config["episodes"] == 3 and config["scenario"] == "low_cov"
