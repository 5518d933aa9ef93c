"""Actor identity and restart with real processes over a Zenoh router.

* An actor killed (SIGKILL) with a spilled outbox that no learner ever saw, restarted with the same id and run
  directory (no ``--resume``): it continues its stream from the outbox on disk, and the learner ends up with
  every transition of both processes exactly once; episodes.csv and corrections.csv are appended to.
* A second process with the id of a live actor is refused (exit code 2, one clear line): by the lock in the
  same run directory, by the live actor's liveliness token from another one; the learner takes one stream of
  that id, each transition once.

The parts without processes: tests/unit/test_outbox.py.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from helpers import ProcGroup, read_json, unique_run, wait_for

FAST = ["--scenario", "low_cov", "--method", "khgrl", "--learning-starts", "16", "--max-lead", "100000"]
BATCH = 8


def rows(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def batch_files(out: Path) -> list[Path]:
    return sorted((out / "outbox").glob("*.msgpack")) if (out / "outbox").is_dir() else []


def buffer_steps(run_dir: Path, actor: str) -> tuple[dict, list[int]]:
    """The learner's final checkpoint: its state, and the running indices of ``actor``'s transitions in the
    replay buffer (sorted; every provenance code of that actor id)."""
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    ck = run_dir / "learner" / "checkpoint"
    state, arrays = read_json(ck / "state.json"), load_checkpoint_arrays(ck)
    pos = state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]
    codes, steps = arrays["provenance_actor"][:pos], arrays["provenance_step"][:pos]
    mine = [c for c, e in enumerate(state["codes"]) if e["actor"] == actor]
    return state, sorted(steps[np.isin(codes, mine)].tolist())


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_actor_killed_with_a_spilled_outbox_continues_its_stream(tmp_path):
    run, run_dir = unique_run("restart"), tmp_path / "run"
    out = run_dir / "actor-a0"
    # 2 batches in memory, the rest spilled; 100 Hz: the scripted human keeps up (it helps in episodes 1 and 3,
    # where they reach its window: random actions throughout, as a policy trained this little stops earlier)
    flags = [*FAST, "--outbox-memory", "2", "--rate", "100", "--episodes", "3", "--learning-starts", "100000"]
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        human = g.human(run, ep, "scripted", "--scenario", "low_cov", "--human-episodes", "1", "3")
        first = g.actor(run, ep, *flags, "--learner-wait", "0")  # no learner yet: nothing is confirmed
        done = wait_for(lambda: rows(out / "episodes.csv"), 180, "episode 1", procs=[first])
        ep1_batches = -(-int(done[0]["steps"]) // BATCH)
        wait_for(lambda: len(batch_files(out)) >= ep1_batches + 3, 60, "batches of episode 2", procs=[first])
        first.kill()
        files_at_kill = len(batch_files(out))
        episodes_before = (out / "episodes.csv").read_text()
        corrections_before = (out / "corrections.csv").read_text()
        corrections_before = corrections_before[:corrections_before.rfind("\n") + 1]  # (a half-written row)
        record = read_json(out / "stream.json")
        assert record["running"] is True and files_at_kill >= ep1_batches + 3

        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0")
        second = g.actor(run, ep, *flags)  # the same id and run directory, no --resume
        assert second.wait(240) == 0, second.tail()
        assert learner.stop(60) == 0, learner.tail()
        human.stop(30)

    summary = read_json(out / "summary.json")
    start = summary["first_index"]
    n = summary["next_index"]
    assert summary["stream"] == record["stream"] and start > 0
    assert summary["episodes"] == 2 and summary["first_episode"] == 2 and n == start + summary["transitions"]
    assert summary["unconfirmed_transitions"] == 0 and summary["durable"] == summary["last_seq"]
    state, got = buffer_steps(run_dir, "a0")
    assert got == list(range(n)), f"not every transition 0..{n - 1} exactly once: {len(got)} in the buffer"
    assert state["total_ingested"] == n and [c["stream"] for c in state["codes"]] == [record["stream"]]
    # the learner started after the kill: the first process's transitions all came from its outbox on disk
    assert start >= BATCH * (files_at_kill - 1)
    episodes = rows(out / "episodes.csv")
    assert [int(r["episode"]) for r in episodes] == [1, 2, 3]
    text = (out / "episodes.csv").read_text()
    assert text.startswith(episodes_before) and text.count("episode,steps") == 1
    # the killed episode's transitions are in the buffer too (cut before the kill), though it has no row
    assert n - sum(int(r["steps"]) for r in episodes) == start - int(episodes[0]["steps"]) > 0
    corrections = (out / "corrections.csv").read_text()
    assert corrections.startswith(corrections_before) and corrections.count("run,actor,episode") == 1
    assert {"1"} <= {r["episode"] for r in rows(out / "corrections.csv")} <= {"1", "3"}
    runtime = read_json(out / "config.json")["runtime"]
    assert runtime["continued_stream"] is True and runtime["after_kill"] is True and runtime["resumed"] is True
    assert not batch_files(out) and read_json(out / "stream.json")["running"] is False


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_second_process_with_a_live_actor_id_is_refused(tmp_path):
    run, run_dir = unique_run("twin"), tmp_path / "run"
    out = run_dir / "actor-a0"
    flags = [*FAST, "--rate", "50", "--episodes", "1000"]  # runs until stopped
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        # (--no-journal: a0's batches stay in its outbox until the end, which shows that it streams)
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0", "--no-journal")
        a0 = g.actor(run, ep, *flags)
        wait_for(lambda: len(batch_files(out)) >= 4, 180, "a0 streaming", procs=[learner, a0])
        same_dir = g.actor(run, ep, *flags)
        assert same_dir.wait(120) == 2, same_dir.tail()
        elsewhere = g.actor(run, ep, *flags, run_dir=tmp_path / "run2")  # as if on another machine
        assert elsewhere.wait(180) == 2, elsewhere.tail()
        assert a0.poll() is None, a0.tail()
        assert a0.stop(60) == 0, a0.tail()
        assert learner.stop(60) == 0, learner.tail()
        texts = same_dir.text(), elsewhere.text()

    lines = [ln for ln in texts[0].splitlines() if ln.startswith("khgrl actor")]
    assert lines == [f"khgrl actor a0: error: actor a0 is already running: another process (pid {a0.pid}) runs this "
                     f"actor with run directory {run_dir} (it holds {out / 'actor.lock'})"], texts[0]
    lines = [ln for ln in texts[1].splitlines() if ln.startswith("khgrl actor")]
    assert len(lines) == 1 and "actor a0 is already alive on the router" in lines[0], texts[1]
    # the refused processes published nothing and left nothing to continue
    assert not (tmp_path / "run2" / "actor-a0" / "stream.json").exists()
    summary = read_json(out / "summary.json")
    n = summary["transitions"]
    state, got = buffer_steps(run_dir, "a0")
    assert got == list(range(n)), f"{len(got)} transitions in the buffer, a0 made {n}"
    assert [c["actor"] for c in state["codes"]] == ["a0"] and state["actors"]["a0"]["next_seq"] == summary["batches"]
    assert json.loads((out / "stream.json").read_text())["stream"] == summary["stream"]


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_paused_actor_replaced_by_a_second_process_is_refused_when_it_wakes(tmp_path):
    """The race the liveliness check cannot close: a0 is stopped (SIGSTOP) long enough for its liveliness token
    to lapse, a second a0 (another run directory) starts and streams, then the first wakes up. The learner
    keeps to the later stream -- never back and forth; the first, seeing the acks of the second's stream of its id
    move on or its own stream superseded, says another process publishes as it and exits 4."""
    import signal

    run, run_dir, run2 = unique_run("pause"), tmp_path / "run", tmp_path / "run2"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        # (--no-journal: the batches stay in the actors' outboxes until the end, which shows that they stream)
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0", "--no-journal")
        first = g.actor(run, ep, *FAST, "--rate", "50", "--episodes", "1000", "--lease-ms", "1000")
        wait_for(lambda: len(batch_files(run_dir / "actor-a0")) >= 4, 180, "a0 streaming", procs=[learner, first])
        first.signal(signal.SIGSTOP)
        second = g.actor(run, ep, *FAST, "--rate", "100", "--episodes", "2", run_dir=run2)
        wait_for(lambda: len(batch_files(run2 / "actor-a0")) >= 4, 180, "the second a0 streaming",
                 procs=[learner, second])
        first.signal(signal.SIGCONT)
        assert first.wait(120) == 4, first.tail()
        assert second.wait(180) == 0, second.tail()
        assert learner.stop(60) == 0, learner.tail()
        text = first.text()

    lines = [ln for ln in text.splitlines() if ln.startswith("khgrl actor")]
    assert len(lines) == 1 and "another process publishes as actor a0" in lines[0], text
    s1 = read_json(run_dir / "actor-a0" / "config.json")["runtime"]["stream"]
    s2 = read_json(run2 / "actor-a0" / "summary.json")
    state, _ = buffer_steps(run_dir, "a0")
    assert [c["stream"] for c in state["codes"]] == [s1, s2["stream"]]  # one switch, never back
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    arrays = load_checkpoint_arrays(run_dir / "learner" / "checkpoint")
    pos = state["replay"]["pos"]
    codes, steps = arrays["provenance_actor"][:pos], arrays["provenance_step"][:pos]
    old = sorted(steps[codes == 0].tolist())
    assert old == list(range(len(old))) and old, "the first a0's transitions: each once, up to where it was taken"
    assert sorted(steps[codes == 1].tolist()) == list(range(s2["transitions"]))
