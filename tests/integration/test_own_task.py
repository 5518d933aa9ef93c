"""A task of the user's own (deploy/examples/own_task.py, O = 3) through the real system: ``khgrl up --task``
runs it with its scripted human and the learner stores 3-D transitions; a learner and an actor of different
tasks refuse each other; the learner refuses a batch of another size."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import REPO, SMALL, ProcGroup, read_json, unique_run, wait_for

OWN = "khgrl.deploy.examples.own_task:make_task"
UP = [sys.executable, "-m", "khgrl.deploy.cli", "up"]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RUST_LOG", "error")
    return env


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_own_3d_task_through_khgrl_up(tmp_path: Path) -> None:
    from khgrl.learner.checkpoint import load_checkpoint_arrays
    from stable_baselines3.common.save_util import load_from_pkl

    run_dir = tmp_path / "run"
    proc = subprocess.run([*UP, "--task", OWN, "--episodes", "2", "--human-episodes", "2", "--learning-starts", "64",
                           *SMALL, "--run-dir", str(run_dir), "--no-progress"], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=360)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    config = read_json(run_dir / "config.json")
    assert config["task"] == OWN
    with open(run_dir / "actor-a0" / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    n = sum(int(r["steps"]) for r in rows)
    assert [int(r["episode"]) for r in rows] == [1, 2]
    assert int(rows[0]["intervention_steps"]) == 0 and int(rows[1]["intervention_steps"]) > 0  # lifted over the box

    ck = run_dir / "learner" / "checkpoint"
    state = read_json(ck / "state.json")
    assert state["total_ingested"] == n
    rb = load_from_pkl(ck / "replay_buffer.pkl")
    assert rb.observations.shape[-1] == 7 and rb.actions.shape[-1] == 3  # env obs (3) + phase + deviation (3); O = 3
    iv = load_checkpoint_arrays(ck)["intervened"][:n].astype(bool)
    assert iv.sum() == int(rows[1]["intervention_steps"])
    acts = rb.actions[:n, 0]
    assert np.all(np.abs(acts) <= 1.0) and np.any(acts[iv, 2] != 0.0)
    with open(run_dir / "actor-a0" / "corrections.csv") as fh:
        corr = list(csv.DictReader(fh))
    assert corr and "p_h_z" in corr[0] and all(float(r["p_h_z"]) >= 0.38 - 1e-9 for r in corr)
    learner_log = (run_dir / "learner" / "learner.log").read_text()
    assert "task point-3d (O = 3, 7 observations" in learner_log


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_learner_and_actor_of_different_tasks_refuse_each_other(tmp_path: Path) -> None:
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Transitions
    from khgrl.common.wire.protocol import Keys, encode

    run, run_dir = unique_run(), tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "50")
        a0 = g.actor(run, ep, "--task", OWN, "--method", "kgrl", "--episodes", "2", "--learning-starts", "50")
        log = run_dir / "learner" / "learner.log"
        wait_for(lambda: "task point-3d" in log.read_text(), 120, "the learner built from the actor's task",
                 procs=[learner])
        # an actor of the passage world (O = 2, 5 observations) joins the 3-D learner: it stops at once, saying why
        a1 = g.actor(run, ep, "--task", "passage:low_cov", "--id", "a1", "--episodes", "1")
        assert a1.wait(120) == 2, a1.tail()
        assert "was built for task 'point-3d' (3 outputs, 7 observations" in a1.tail()
        # a batch of passage-world sizes on the wire is refused by the learner (counted, logged), not trained on
        tr = Transitions(actor="x1", first_step=0, obs=np.zeros((2, 5), np.float32),
                         next_obs=np.zeros((2, 5), np.float32), action=np.zeros((2, 2), np.float32),
                         reward=np.zeros(2, np.float32), terminated=np.zeros(2, np.uint8),
                         truncated=np.zeros(2, np.uint8), intervened=np.zeros(2, np.uint8),
                         clipped=np.zeros(2, np.uint8), task="0123456789abcdef")
        with open_client(ep, 3000) as s:
            s.put(Keys(run).transitions("x1"), encode(tr, "x1", 0))
            time.sleep(1.0)
        wait_for(lambda: "rejected transitions" in log.read_text(), 30, "the learner's reject line", procs=[learner])
        assert a0.wait(200) == 0, a0.tail()
        assert learner.stop(60) == 0, learner.tail()
    text = log.read_text()
    assert "obs: expected shape (None, 7)" in text
    state = read_json(run_dir / "learner" / "checkpoint" / "state.json")
    assert [c["actor"] for c in state["codes"]] == ["a0"]  # nothing of a1 or x1 was stored
