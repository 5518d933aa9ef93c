"""Floods and many actors with real processes: 100,000 garbage messages on an actor's correction and control keys
while it runs at 50 Hz (it keeps stepping, logs a handful of lines, nothing dies); and robot mode with several
actors that never wait, every transition in the learner's checkpoint exactly once."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
from test_learner_actor import assert_exactly_once, checkpoint

from helpers import REPO, ProcGroup, read_json, unique_run, wait_for

pytestmark = pytest.mark.integration

FAST = ["--scenario", "low_cov", "--method", "khgrl", "--learning-starts", "16"]

FLOOD = textwrap.dedent("""
    import os, sys, time
    from khgrl.common.delivery.transport import open_client
    endpoint, run, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    with open_client(endpoint, timeout=20) as s:
        pubs = [s.declare_publisher(f"khgrl/{run}/human/flood/correction"),
                s.declare_publisher(f"khgrl/{run}/control/all")]
        time.sleep(0.5)
        t0 = time.monotonic()
        for i in range(n):
            pubs[i % 2].put(os.urandom(1 + i % 64))
        print(f"{n} messages in {time.monotonic() - t0:.1f} s", flush=True)
        time.sleep(1.0)
""")


@pytest.mark.timeout(400)
def test_a_100k_message_flood_does_not_stop_the_actor_loop(tmp_path):
    run, run_dir = unique_run(), tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0")
        actor = g.actor(run, ep, *FAST, "--episodes", "3", "--max-lead", "100000", "--rate", "50")
        status = run_dir / "actor-a0" / "episodes.csv"
        wait_for(lambda: len(status.read_text().splitlines()) >= 2, 180, "a first episode", procs=[learner, actor])
        done = subprocess.run([sys.executable, "-c", FLOOD, ep, run, "100000"], cwd=REPO, capture_output=True,
                              text=True, timeout=200, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
        assert done.returncode == 0, done.stderr
        rc = actor.wait(200)
        assert rc == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()
    summary = read_json(run_dir / "actor-a0" / "summary.json")
    assert summary["episodes"] == 3 and summary["unconfirmed_transitions"] == 0
    rejected = sum(summary["rejects"].values())
    # the flood arrived: the actor read more than its correction and control/all rings hold (256 + 16 newest; the
    # rest of a flood overflows them uncounted). How many more depends on how long the sender takes against the
    # loop's 16 messages a step -- on a fast machine 100,000 puts take well under a second -- so no more is asked.
    assert rejected > 256 + 16, summary["rejects"]
    log_lines = (run_dir / "actor-a0" / "actor.log").read_text().count("rejected")
    assert log_lines <= 2 * 32 + 10, f"{log_lines} reject lines for {rejected}"  # 32 reasons a kind, then 1 per 10 s
    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", summary["transitions"])


@pytest.mark.timeout(400)
def test_robot_mode_actors_never_wait_and_nothing_is_lost(tmp_path):
    run, run_dir = unique_run(), tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0", "--mode", "robot")
        run_dir.mkdir(parents=True, exist_ok=True)
        g.supervise(run, ep, run_dir)  # (robot mode: the actors move only while supervised)
        actors = [g.actor(run, ep, *FAST, "--episodes", "2", "--rate", "0", "--mode", "robot", "--window", "4",
                          "--id", f"a{i}", "--seed", str(i)) for i in range(3)]
        for a in actors:
            assert a.wait(250) == 0, a.tail()
        assert learner.stop(60) == 0, learner.tail()
    state, arrays = checkpoint(run_dir)
    total = 0
    for i in range(3):
        summary = read_json(run_dir / f"actor-a{i}" / "summary.json")
        assert summary["rate_limit"]["waits"] == 0 and summary["unconfirmed_transitions"] == 0
        assert_exactly_once(state, arrays, f"a{i}", summary["transitions"])
        total += summary["transitions"]
    assert state["total_ingested"] == total and not state["due"]
    assert state["iterations"] > 0
