"""The HIL-SERL baseline (``--method hil-serl``) and RLPD replay (``--sampling rlpd``) in the real system.

Two real runs serve every assertion (CI time):

* the passage world started by hand (router, learner, actor, scripted human; ``--method hil-serl``): the learner
  is SIGKILLed once the demonstrations are in and restarted with ``--resume``. Every transition -- demonstrations,
  the human's takeover, the policy's -- is in the buffer exactly once, the prior data (the intervened slots)
  included; the takeover stored the action towards the human's P_h (recomputed here from corrections.csv and the
  stored observation), and half of every minibatch came from the prior data (the buffer's own counts);
* the 3-D example task through ``khgrl up`` under ``--method hil-serl``, at update-to-data ratio 2
  (``--gradient-steps 16``): the achieved ratio equals the setting, half of each batch is prior data, and
  ``khgrl eval`` evaluates the HIL-SERL policy under its own (delta) control.
"""

from __future__ import annotations

import csv
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from test_learner_actor import assert_exactly_once, checkpoint
from test_sac import CLI, OWN, _env

from helpers import REPO, SMALL, ProcGroup, read_json, unique_run, wait_for


def _rows(path: Path) -> list[dict]:
    with open(path) as fh:
        return list(csv.DictReader(fh))


def _buffer(run_dir: Path):
    from stable_baselines3.common.save_util import load_from_pkl

    return load_from_pkl(run_dir / "learner" / "checkpoint" / "replay_buffer.pkl")  # (our own file on local disk)


def _prior_share(rb) -> float:
    return rb.sampled_prior / max(1, rb.sampled_prior + rb.sampled_online)


def _check_takeover(run_dir: Path, spec: str, demo_transitions: int) -> int:
    """Every takeover step stored a_h = clip((clip(P_h) - position) / step); returns how many were checked."""
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    env = KGRLEnv(load_task(spec), control="delta")
    low, high, step = env.world.low, env.world.high, env.delta.step
    rb = _buffer(run_dir)
    episodes = _rows(run_dir / "actor-a0" / "episodes.csv")
    first = {int(r["episode"]): demo_transitions + sum(int(e["steps"]) for e in episodes[:i])
             for i, r in enumerate(episodes)}  # the stream index of each episode's step 0
    slot = {int(i): s for s, i in enumerate(rb.provenance_step[:rb.pos])}
    o = env.world.out_dim
    checked = 0
    for c in _rows(run_dir / "actor-a0" / "corrections.csv"):
        s = slot[first[int(c["episode"])] + int(c["step"])]
        assert rb.intervened[s] == 1
        p_h = np.clip([float(c[k]) for k in sorted(k for k in c if k.startswith("p_h_"))][:o], low, high)
        position = env.task.position(rb.observations[s, 0, :-1 - o].astype(np.float64))
        want = np.clip((p_h - position) / step, -1.0, 1.0)
        np.testing.assert_allclose(rb.actions[s, 0], want, atol=2e-4, err_msg=f"takeover at {c['episode']}/{c['step']}")
        checked += 1
    return checked


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_hilserl_passage_takeover_prior_data_and_learner_kill(tmp_path):
    run, run_dir = unique_run("hil"), tmp_path / "run"
    state_file = run_dir / "learner" / "checkpoint" / "state.json"
    # random actions until transition 2200: the demonstrations (~1700) and episode 1, where the human takes over
    learner_flags = ["--algo", "sac_ln", "--sampling", "rlpd", "--learning-starts", "2200", "--checkpoint-every",
                     "256"]
    world = ["--scenario", "low_cov", "--method", "hil-serl"]
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, *learner_flags)
        human = g.human(run, ep, "scripted", *world, "--human-episodes", "1")
        actor = g.actor(run, ep, *world, "--learning-starts", "2200", "--episodes", "3", "--max-lead", "100000",
                        "--rate", "150")
        wait_for(lambda: read_json(state_file)["total_ingested"] >= 1800, 150, "the demonstrations in a checkpoint",
                 procs=[learner, actor])
        learner.kill()
        killed_at = read_json(state_file)["total_ingested"]
        time.sleep(0.5)
        learner = g.learner(run, ep, *learner_flags, "--resume")
        assert actor.wait(250) == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()
        human.stop(20)

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n, demos = summary["transitions"], summary["demo_transitions"]
    assert summary["unconfirmed_transitions"] == 0 and n > killed_at and demos > 0
    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)  # 0 lost, 0 duplicated across the kill: prior and online data
    episodes = _rows(run_dir / "actor-a0" / "episodes.csv")
    human_steps = sum(int(r["intervention_steps"]) for r in episodes)
    assert demos + sum(int(r["steps"]) for r in episodes) == n
    assert int(episodes[0]["intervention_steps"]) > 0 and human_steps == int(episodes[0]["intervention_steps"])
    # the prior data are exactly the demonstrations and the takeover steps, all in the buffer after the resume
    assert int(arrays["intervened"][:n].sum()) == demos + human_steps
    assert _check_takeover(run_dir, "passage:low_cov", demos) == human_steps
    rb = _buffer(run_dir)
    assert rb.sampled_prior > 0 and _prior_share(rb) == pytest.approx(0.5), (rb.sampled_prior, rb.sampled_online)
    assert state["algo"] == "sac_ln" and "sac_ln resumed from" in (run_dir / "learner" / "learner.log").read_text()
    assert read_json(run_dir / "actor-a0" / "config.json")["method"] == "hil-serl"


@pytest.mark.integration
@pytest.mark.timeout(500)
def test_rlpd_on_a_3d_task_through_khgrl_up(tmp_path):
    """(``--method khgrl --sampling rlpd`` ran here too until 2026-12-06: TQC's buffer with RLPD sampling is
    tests/unit/test_replay_rlpd.py's, the same path through ``khgrl up`` at UTD 2 is this run's.)"""
    run_dir, starts = tmp_path / "run", 1024  # training starts near the demonstrations' end (1,097): CI time
    proc = subprocess.run([*CLI, "up", "--task", OWN, "--method", "hil-serl", "--episodes", "3", "--human-episodes",
                           "2", "--learning-starts", str(starts), *SMALL, "--gradient-steps", "16", "--seed", "2",
                           "--run-dir", str(run_dir), "--no-progress"], cwd=REPO, env=_env(), capture_output=True,
                          text=True, timeout=400)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    cfg = read_json(run_dir / "config.json")
    assert cfg["tqc"]["sampling"] == "rlpd" and cfg["algo"] == "sac_ln"
    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n, demos = summary["transitions"], summary["demo_transitions"]
    episodes = _rows(run_dir / "actor-a0" / "episodes.csv")
    assert demos > 0 and demos + sum(int(r["steps"]) for r in episodes) == n
    state, arrays = checkpoint(run_dir)
    assert_exactly_once(state, arrays, "a0", n)
    human_steps = sum(int(r["intervention_steps"]) for r in episodes)
    assert human_steps > 0 and int(arrays["intervened"][:n].sum()) == demos + human_steps
    # the achieved update-to-data ratio is the setting: 16 gradient steps per 8 transitions past learning_starts
    assert state["gradient_steps"] == 16 * state["iterations"] and n - starts > 400
    assert state["iterations"] == (n - starts) // 8, (state["iterations"], n)
    assert state["gradient_steps"] / (n - starts) == pytest.approx(2.0, abs=16 / (n - starts))
    rb = _buffer(run_dir)
    assert _prior_share(rb) == pytest.approx(0.5) and rb.sampled_prior + rb.sampled_online == 64 * state[
        "gradient_steps"]
    assert _check_takeover(run_dir, OWN, demos) == human_steps
    assert all(int(r["workspace_exits"]) >= 0 for r in episodes) and "violation_steps" in episodes[0]
    out = subprocess.run([*CLI, "eval", str(run_dir), "--episodes", "1"], cwd=REPO, env=_env(),
                         capture_output=True, text=True, timeout=200)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
