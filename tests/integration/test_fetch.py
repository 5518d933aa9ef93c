"""The Fetch arm task (gymnasium-robotics, MuJoCo) through the real system: ``khgrl up --task fetch:moved`` with
its scripted human, 2 short episodes; the learner stores 3-D transitions (28 + 1 + 3 observations), the human's
correction at the grasp drags the gripper toward the moved object and raises L there."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import REPO, SMALL, read_json, untimed

pytest.importorskip("gymnasium_robotics", reason="gymnasium-robotics is a project dependency: pip install -e .")


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_fetch_moved_through_khgrl_up(tmp_path: Path) -> None:
    from khgrl.common.tasks.fetch.task import DEMO_OBJECT, MOVE
    from stable_baselines3.common.save_util import load_from_pkl

    run_dir = tmp_path / "run"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error"}
    proc = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "up", "--task", "fetch:moved", "--episodes", "2",
                           "--human-episodes", "2", "--learning-starts", "64", "--run-dir", str(run_dir),
                           "--no-progress", *SMALL], cwd=REPO, env=env, capture_output=True, text=True, timeout=360)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    with open(run_dir / "actor-a0" / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["steps"]) for r in rows] == [100, 100]  # Fetch does not terminate: the KMP horizon ends it
    assert int(rows[0]["intervention_steps"]) == 0 and int(rows[1]["intervention_steps"]) > 0
    rb = load_from_pkl(run_dir / "learner" / "checkpoint" / "replay_buffer.pkl")
    assert rb.observations.shape[-1] == 32 and rb.actions.shape[-1] == 3
    assert read_json(run_dir / "learner" / "checkpoint" / "state.json")["total_ingested"] == 200
    with open(run_dir / "actor-a0" / "corrections.csv") as fh:
        corr = list(csv.DictReader(fh))
    p_h = np.array([[float(r["p_h_x"]), float(r["p_h_y"]), float(r["p_h_z"])] for r in corr])
    moved = DEMO_OBJECT + MOVE
    assert np.all(np.abs(p_h[:, 1] - moved[1]) < 0.03)  # the human holds the gripper at the moved object's y
    scale = np.load(run_dir / "actor-a0" / "scale.npz")["table"]
    assert scale.max() > 100 * scale.min()  # L raised at the grasp, the default elsewhere


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_seeded_fetch_runs_give_the_same_episodes(tmp_path: Path) -> None:
    """Two seeded runs, the same episodes. Fetch's episodes are 100 steps, learning_starts 100 and train_freq 8:
    the first episode's last batch is short, and the actor used to take the first due iteration's steps (104..)
    with the initial weights whenever the ack of its batch came late (``Trainer.ack``): episode 2 then depended on
    timing. Every policy step runs with weights at most ``train_freq - 1`` transitions behind (max_lag)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error"}
    runs = []
    for i in range(2):
        run_dir = tmp_path / f"run{i}"
        proc = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "up", "--task", "fetch:moved", "--method",
                               "khgrl", "--episodes", "2", "--seed", "0", "--run-dir", str(run_dir), "--no-progress",
                               *SMALL],
                              cwd=REPO, env=env, capture_output=True, text=True, timeout=180)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        weights = read_json(run_dir / "actor-a0" / "summary.json")["weights"]
        assert weights["max_lag"] <= 7, weights  # no step of episode 2 with the initial weights
        with open(run_dir / "actor-a0" / "episodes.csv") as fh:
            runs.append(untimed(list(csv.DictReader(fh))))
    assert [int(r["steps"]) for r in runs[0]] == [100, 100]
    assert runs[0] == runs[1]
