"""Record and replay of human corrections.

The actor records every correction it applies to ``RUN_DIR/actor-ID/corrections.csv``; ``khgrl human replay FILE``
feeds such a record into a new run. Integration: run 1 (router + actor + scripted human) records a session; run 2
(a new run id, same seeds, a fresh actor) is driven by the replay client alone and intervenes at exactly the same
episodes and steps with the same P_h. The actors run without a learner (random warm-up policy for the whole run,
so both runs act identically apart from the corrections); their final flush then times out (exit code 3).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from helpers import ProcGroup, RecordingPublisher, unique_run


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_plan_leads_by_one_step(tmp_path):
    from khgrl.human_bridge.replay import ReplayPlan, load_record

    p = tmp_path / "corrections.csv"
    p.write_text("run,actor,episode,step,time,client,p_h_x,p_h_y,projected,clipped\n"
                 "r,a0,2,10,1.0,x,0.5,0.25,0,0\n"
                 "r,a0,2,11,1.1,x,0.5,0.5,0,1\n"
                 "r,a1,1,3,1.2,x,0.1,0.1,0,0\n")
    rows = load_record(p)
    assert [(r["actor"], r["episode"], r["step"]) for r in rows] == [("a0", 2, 10), ("a0", 2, 11), ("a1", 1, 3)]
    plan = ReplayPlan(rows)
    assert plan.source == "a0" and plan.last == (2, 11)
    assert plan.correction(2, 8) is None
    np.testing.assert_array_equal(plan.correction(2, 9), [0.5, 0.25])  # frame of step 9 -> applies at step 10
    np.testing.assert_array_equal(plan.correction(2, 10), [0.5, 0.5])
    assert plan.correction(2, 11) is None and plan.correction(1, 9) is None
    assert not plan.finished(2, 10) and plan.finished(2, 11) and plan.finished(3, 0)
    assert ReplayPlan(rows, "a1").steps == {(1, 3): pytest.approx(np.array([0.1, 0.1]))}
    bad = tmp_path / "bad.csv"
    bad.write_text("run,actor,episode,step,time,client,p_h_x,p_h_y\nr,a0,1,1,0,x,nan,0\n")
    with pytest.raises(ValueError):
        load_record(bad)


def _frame(episode: int, t: int):
    from khgrl.common.wire.protocol import Frame

    p = np.array([0.5, 0.5])
    return Frame(actor="a0", episode=episode, t=t, phase=0.5, robot=p, desired=p, mean=p, scale=np.array([1.0, 1.0]),
                 intervening=False, task="passage-low_cov")


def test_replay_answers_each_frame_with_the_recorded_word_for_the_next_step():
    from khgrl.human_bridge.replay import ReplayAnswers, ReplayPlan

    rows = [{"actor": "a0", "episode": 2, "step": s, "p_h": np.array([0.1 * s, 0.5]), "client": "x"} for s in (0, 1, 3)]
    stream = RecordingPublisher()
    answers = ReplayAnswers(ReplayPlan(rows), stream, "a1")
    assert not answers.frame(_frame(1, 7))  # episode 1: announce episode 2 with its step 0's word
    addressed = [m for m in stream.sent if m[4] is not None]  # (live words only release a hold, if any)
    assert addressed == [("a1", (0.0, 0.5), 2, 7, 0)]
    done = [answers.frame(_frame(2, t)) for t in range(5)]
    addressed = [m[1:] for m in stream.sent if m[4] is not None]
    assert addressed[1:] == [((0.1, 0.5), 2, 0, 1), (None, 2, 1, 2), ((0.1 * 3, 0.5), 2, 2, 3), (None, 2, 3, 4),
                             (None, 2, 4, 5)]
    assert done == [False, False, False, True, True] and answers.sent_steps == 2


# as fast as allowed (no --rate): step-addressed corrections keep the record and the replay on their steps
ACTOR = ["--scenario", "low_cov", "--method", "khgrl", "--episodes", "2",
         "--learning-starts", "100000", "--flush-timeout", "0.5", "--learner-wait", "0"]


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_replay_reproduces_the_recorded_interventions(tmp_path):
    run1, run2 = unique_run("rec"), unique_run("rep")
    dir1, dir2 = tmp_path / "run1", tmp_path / "run2"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        # run 1: the scripted human corrects in episode 2
        actor = g.actor(run1, ep, *ACTOR, run_dir=dir1)
        human = g.human(run1, ep, "scripted", "--scenario", "low_cov", "--actor", "*", "--human-episodes", "2")
        assert actor.wait(150) == 3, actor.tail()  # no learner: the flush times out, everything else is done
        human.stop(10)
        record = dir1 / "actor-a0" / "corrections.csv"
        rec1 = _rows(record)
        assert rec1 and {r["client"] for r in rec1} == {"scripted"} and {r["episode"] for r in rec1} == {"2"}
        # run 2: a new run, driven by the replay of run 1's record
        replay = g.human(run2, ep, "replay", str(record), "--wait", "120")
        actor2 = g.actor(run2, ep, *ACTOR, run_dir=dir2)
        assert actor2.wait(150) == 3, actor2.tail()
        assert replay.wait(30) == 0, replay.tail()
        assert "sent" in replay.tail()
    rec2 = _rows(dir2 / "actor-a0" / "corrections.csv")
    assert {r["client"] for r in rec2} == {"replay"}
    steps1 = [(int(r["episode"]), int(r["step"])) for r in rec1]
    steps2 = [(int(r["episode"]), int(r["step"])) for r in rec2]
    assert steps2 == steps1, f"replayed steps differ: only in record {sorted(set(steps1) - set(steps2))[:10]}, " \
                             f"only in replay {sorted(set(steps2) - set(steps1))[:10]}"
    p1 = np.array([[float(r["p_h_x"]), float(r["p_h_y"])] for r in rec1])
    p2 = np.array([[float(r["p_h_x"]), float(r["p_h_y"])] for r in rec2])
    np.testing.assert_array_equal(p2, p1)
    # the same episodes came out of it (same interventions, same trajectories)
    e1, e2 = _rows(dir1 / "actor-a0" / "episodes.csv"), _rows(dir2 / "actor-a0" / "episodes.csv")
    for a, b in zip(e1, e2, strict=True):
        for k in ("episode", "steps", "interventions", "intervention_steps", "clipped_steps", "success"):
            assert a[k] == b[k], (k, a, b)
        assert float(a["ret"]) == pytest.approx(float(b["ret"]), rel=1e-9)


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_up_runs_the_replay_client_from_the_run_setting(tmp_path):
    """khgrl up --human replay --replay FILE: every client of khgrl human is a choice of --human (the hand-kept list
    lacked replay); the replay client started by khgrl up (--config only) reads the record from the run setting."""
    import subprocess
    import sys

    record = tmp_path / "corrections.csv"
    steps = range(100, 121)
    record.write_text("run,actor,episode,step,time,client,p_h_x,p_h_y,projected,clipped\n" + "".join(
        f"old,a0,1,{t},0.0,gui,0.35,0.55,0,0\n" for t in steps))
    run_dir = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "up", "--scenario", "low_cov", "--episodes", "1",
                          "--human", "replay", "--replay", str(record), "--learning-starts", "100000",
                          "--no-progress", "--run-dir", str(run_dir)], capture_output=True, text=True, timeout=200)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    rows = _rows(run_dir / "actor-a0" / "corrections.csv")
    assert {r["client"] for r in rows} == {"replay"}
    assert [(int(r["episode"]), int(r["step"])) for r in rows] == [(1, t) for t in steps]
    assert all((float(r["p_h_x"]), float(r["p_h_y"])) == (0.35, 0.55) for r in rows)
