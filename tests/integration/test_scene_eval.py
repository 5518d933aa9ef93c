"""``khgrl eval --scenes`` on a run of the real processes: a user's task whose scene changes every episode
(tests/scene_point_task.py, copied into a scratch folder as a user would) trained by ``khgrl up`` for a few episodes,
then evaluated on 8 seeded scenes, twice with the same seed."""

from __future__ import annotations

import csv
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from khgrl.common.tasks.scene import scene_seed
from khgrl.deploy.tools.intervals import rate_text

from helpers import REPO, SMALL, kill_pids, pid_alive, read_json


def _run(args: list[str], cwd: Path, timeout: float) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error", "PYTHONPATH": "", "SDL_VIDEODRIVER": "dummy"}
    return subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_khgrl_up_then_eval_on_seeded_scenes(tmp_path: Path) -> None:
    shutil.copy(REPO / "tests" / "scene_point_task.py", tmp_path / "scene_point_task.py")
    run = tmp_path / "runs" / "pts"
    try:
        up = _run(["up", "--task", "scene_point_task:make_task", "--human", "none", "--episodes", "3",
                   "--learning-starts", "40", "--seed", "2", "--run-dir", "runs/pts", "--no-progress", *SMALL],
                  tmp_path, 200)
    finally:
        if (run / "pids.json").exists():
            kill_pids([p for p in read_json(run / "pids.json")["children"].values() if pid_alive(p)])
    assert up.returncode == 0, up.stdout[-2000:] + up.stderr[-2000:]
    assert len(_rows(run / "actor-a0" / "episodes.csv")) == 3

    first = _run(["eval", "runs/pts", "--scenes", "8", "--gif", "scenes.gif"], tmp_path, 120)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    rows = _rows(run / "eval" / "scenes.csv")
    assert [int(r["scene"]) for r in rows] == list(range(1, 9))
    assert [int(r["seed"]) for r in rows] == [scene_seed(2, k, stream="eval") for k in range(1, 9)]  # the run's seed
    placements = [(float(r["goal_x"]), float(r["goal_y"])) for r in rows]
    assert len(set(placements)) == 8 and all(0.7 <= x <= 0.9 and 0.3 <= y <= 0.7 for x, y in placements)
    k = sum(r["success"] == "True" for r in rows)
    printed = re.search(r"^success (\d+/\d+ = .*Wilson\))", first.stdout, re.M)
    assert printed and printed.group(1) == rate_text(k, 8), first.stdout  # the printed interval is the CSV's
    assert "frames of scenes 1-3)" in first.stdout and (tmp_path / "scenes.gif").stat().st_size > 0

    # the same seed: the same scenes (a paired comparison across runs; another seed's: tests/unit/test_eval_scenes.py)
    again = _run(["eval", "runs/pts", "--scenes", "8", "--seed", "2"], tmp_path, 120)
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
    assert _rows(run / "eval" / "scenes-2.csv") == rows  # (a deterministic policy: the results too)

    # --task: the run's policy on another task with the same spaces (here the run's own, named) gives the same
    # scenes and results; a task with other spaces is refused in one line
    same = _run(["eval", "runs/pts", "--scenes", "8", "--seed", "2", "--task", "scene_point_task:make_task"],
                tmp_path, 120)
    assert same.returncode == 0 and _rows(run / "eval" / "scenes-3.csv") == rows, same.stdout + same.stderr
    other = _run(["eval", "runs/pts", "--scenes", "2", "--task", "passage:low_cov"], tmp_path, 120)
    assert other.returncode == 2 and other.stderr.count("\n") == 1 and "khgrl eval: error:" in other.stderr, \
        other.stdout[-2000:] + other.stderr[-2000:]
