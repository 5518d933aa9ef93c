"""Physical corrections with real processes: ``khgrl up --task panda:pick --physical scripted`` -- gym-hil's Panda
(a real MuJoCo arm under operational-space control) pushed by the scripted physical human in episode 2 only.

The actor sees positions only. The test checks that it detected the push in episode 2 and nothing in episodes 1
and 3, that every detected step became an intervened transition whose P_h (corrections.csv, ``source`` physical)
is the arm's measured position, and that the learner holds every transition.
"""

from __future__ import annotations

import csv

import numpy as np
import pytest

from helpers import SMALL, read_json
from launch import _run

pytestmark = pytest.mark.integration

ARGS = ["--task", "panda:pick", "--no-adapt", "--method", "khgrl", "--physical", "scripted", "--human", "none",
        "--episodes", "3", "--human-episodes", "2", "--seed", "0", "--learning-starts", "64", "--rate-limit", "on",
        "--max-speed", "1", "--no-progress", *SMALL]


def _csv(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.timeout(300)
def test_a_push_on_a_mujoco_arm_becomes_a_correction(tmp_path):
    from khgrl.actor.physical import detection
    from khgrl.benchmarks.scale import provenance_check

    run = tmp_path / "run"
    done = _run(run, *ARGS, timeout=280)
    assert done.returncode == 0, done.stdout + done.stderr
    steps = _csv(run / "actor-a0" / "physical.csv")
    d = detection(steps)
    print(d)
    assert d["pushed"] > 10 and d["quiet_episodes"] == 2 and d["false_in_quiet_episodes"] == 0, d
    assert d["recall"] > 0.3 and d["precision"] > 0.8 and d["delay_steps"] and max(d["delay_steps"]) <= 8, d
    detected = [(int(r["episode"]), int(r["step"])) for r in steps if r["detected"] == "1"]
    rows = _csv(run / "actor-a0" / "corrections.csv")
    assert rows and {r["source"] for r in rows} == {"physical"} and {r["client"] for r in rows} == {"physical"}
    applied = [(int(r["episode"]), int(r["step"])) for r in rows]
    taken = {(int(r["episode"]), int(r["step"])) for r in steps}
    assert applied == [(e, t + 1) for e, t in detected if (e, t + 1) in taken]  # detected at t: corrected at t + 1
    assert {e for e, _ in applied} == {2}
    eps = _csv(run / "actor-a0" / "episodes.csv")
    assert [int(e["intervention_steps"]) for e in eps] == [0, len(applied), 0]
    by_step = {(int(r["episode"]), int(r["step"])): r for r in steps}
    for r in rows[:5]:  # P_h is where the arm was measured after the step before (its deviation was logged then)
        assert by_step[(int(r["episode"]), int(r["step"]) - 1)]["detected"] == "1"
        assert np.all(np.isfinite([float(r["p_h_x"]), float(r["p_h_y"]), float(r["p_h_z"])]))
    summary = read_json(run / "actor-a0" / "summary.json")
    assert summary["physical"]["detected_steps"] == d["detected"] and summary["physical"]["interactions"] >= 1
    acct = provenance_check(run)
    assert acct["lost"] == 0 and acct["duplicated"] == 0, acct
