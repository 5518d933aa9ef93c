"""``--algo sac`` (learner/sac.py, SB3's SAC through the learner-algorithm interface) in the real system.

Two real runs serve every assertion (CI time): the passage world started by hand (router, learner, actor: 3
episodes), whose learner is SIGKILLed after its first checkpoint and restarted with ``--resume`` (the kill/resume
check of test_learner_actor.py: every transition in the buffer exactly once); and the 3-D example task through
``khgrl up --algo sac`` (3 episodes, the scripted human in one), evaluated by ``khgrl eval``.
"""

from __future__ import annotations

import csv
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_learner_actor import FAST, assert_exactly_once, checkpoint

from helpers import REPO, SMALL, ProcGroup, read_json, unique_run, wait_for

OWN = "khgrl.deploy.examples.own_task:make_task"
CLI = [sys.executable, "-m", "khgrl.deploy.cli"]


def _env() -> dict:
    import os

    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RUST_LOG", "error")
    return env


def _episodes(actor_dir: Path) -> list[dict]:
    with open(actor_dir / "episodes.csv") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_sac_passage_world_survives_a_learner_kill(tmp_path):
    run, run_dir = unique_run("sac"), tmp_path / "run"
    state_file = run_dir / "learner" / "checkpoint" / "state.json"
    sac = ["--algo", "sac", "--learning-starts", "16"]
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, *sac, "--checkpoint-every", "64")
        actor = g.actor(run, ep, *FAST, *sac, "--episodes", "3", "--max-lead", "100000", "--rate", "120")
        wait_for(lambda: read_json(state_file)["total_ingested"] >= 128, 120, "a first checkpoint",
                 procs=[learner, actor])
        learner.kill()
        killed_at = read_json(state_file)["total_ingested"]
        time.sleep(0.5)
        learner = g.learner(run, ep, *sac, "--checkpoint-every", "64", "--resume")
        assert actor.wait(200) == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n = summary["transitions"]
    assert summary["episodes"] == 3 and [int(r["episode"]) for r in _episodes(run_dir / "actor-a0")] == [1, 2, 3]
    assert summary["unconfirmed_transitions"] == 0 and summary["resends"] >= 1 and n > killed_at
    # the actor ran SAC's policy network and took the SAC learner's weights (none refused)
    assert summary["weights"]["final_version"] > 0 and "weights" not in summary["rejects"], summary
    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)  # 0 lost, 0 duplicated across the kill
    assert state["algo"] == "sac" and state["total_ingested"] == n and state["gradient_steps"] > 0
    assert "sac resumed from" in (run_dir / "learner" / "learner.log").read_text()
    assert read_json(run_dir / "actor-a0" / "config.json")["algo"] == "sac"


@pytest.mark.integration
@pytest.mark.timeout(500)
def test_sac_own_3d_task_through_khgrl_up_and_eval(tmp_path):
    from stable_baselines3 import SAC

    run_dir = tmp_path / "run"
    proc = subprocess.run([*CLI, "up", "--algo", "sac", "--task", OWN, "--episodes", "3", "--human-episodes", "2",
                           "--learning-starts", "64", *SMALL, "--run-dir", str(run_dir), "--no-progress"],
                          cwd=REPO, env=_env(), capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert read_json(run_dir / "config.json")["algo"] == "sac"
    rows = _episodes(run_dir / "actor-a0")
    assert [int(r["episode"]) for r in rows] == [1, 2, 3] and int(rows[1]["intervention_steps"]) > 0
    ck = run_dir / "learner" / "checkpoint"
    state = read_json(ck / "state.json")
    assert state["algo"] == "sac" and state["total_ingested"] == sum(int(r["steps"]) for r in rows)
    model = SAC.load(ck / "model.zip", device="cpu")  # SB3's own SAC reads the checkpoint
    assert model.observation_space.shape == (7,) and model.action_space.shape == (3,)

    out = subprocess.run([*CLI, "eval", str(run_dir), "--episodes", "2"], cwd=REPO, env=_env(), capture_output=True,
                         text=True, timeout=200)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "task point-3d" in out.stdout and "learned by actor-a0" in out.stdout and "success " in out.stdout
    with open(run_dir / "eval" / "eval.csv") as fh:
        assert [int(r["episode"]) for r in csv.DictReader(fh)] == [1, 2]
