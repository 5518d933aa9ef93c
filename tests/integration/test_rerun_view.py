"""``khgrl up --view rerun:FILE.rrd`` through the real processes, read back with Rerun's own reader, and ``khgrl view
RUN_DIR --out`` on the same run: the robot at every (episode, step) is the one of the step records, the band has a
point per step, P_h is there at exactly the intervened steps with corrections.csv's values, the returns are
episodes.csv's, and on Fetch MuJoCo's camera images are in it. One short run per task."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import REPO, SMALL, read_json
from rrd_read import by_episode, by_step, read_rrd

pytest.importorskip("rerun", reason="the view needs rerun-sdk (pip install -e '.[test]' has it)")

F32 = dict(rtol=1e-6, atol=1e-6)  # Rerun keeps positions as float32


def _khgrl(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error"}
    return subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


def _rows(path: Path, delimiter: str = ",") -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh, delimiter=delimiter))


def _check_recording(rrd: Path, run_dir: Path, live: bool) -> dict:
    """The recording against the run's records; returns its rows by entity."""
    from khgrl.common.step_records import read_steps

    recordings, rows = read_rrd(rrd)
    assert [(r.application_id, r.recording_id) for r in recordings] == [("khgrl", read_json(run_dir / "config.json")
                                                                          ["runtime"]["run"])]
    actor_dir = run_dir / "actor-a0"
    steps = read_steps(actor_dir)
    robot = by_step(rows["/actor/a0/robot"], "Points3D:positions")
    p_h = by_step(rows["/actor/a0/p_h"], "Points3D:positions")
    o = steps[0]["robot"].shape[1]
    want_robot, want_ph = {}, {}
    for arrays in steps:
        ep = int(arrays["episode"])
        for i, t in enumerate(arrays["t"]):
            want_robot[(ep, int(t))] = arrays["robot"][i]
            if arrays["intervened"][i]:
                want_ph[(ep, int(t))] = arrays["p_h"][i]
    assert sorted(robot) == sorted(want_robot)
    for k, v in want_robot.items():
        np.testing.assert_allclose(robot[k][:o], v, **F32)
        assert np.all(robot[k][o:] == 0)  # a 2-D task at z = 0
    # P_h at exactly the intervened steps, equal to corrections.csv's
    corrections = {(int(r["episode"]), int(r["step"])): np.array([float(r[f"p_h_{a}"]) for a in "xyz"[:o]])
                   for r in _rows(actor_dir / "corrections.csv")}
    assert want_ph and sorted(p_h) == sorted(want_ph) == sorted(corrections)
    for k, v in corrections.items():
        np.testing.assert_allclose(p_h[k][:o], v, **F32)
    # the band: a low and a high edge with a point per step of the episode
    n_steps = {int(a["episode"]): len(a["t"]) for a in steps}
    bands = {int(r["episode"]): r["LineStrips3D:strips"] for r in rows["/actor/a0/band"]}
    assert sorted(bands) == sorted(n_steps)
    for ep, strips in bands.items():
        assert [len(s) for s in strips] == [n_steps[ep], n_steps[ep]]
        low, high = np.asarray(strips[0]), np.asarray(strips[1])
        assert np.all(high >= low - 1e-6)
    # returns and successes per episode: episodes.csv's
    episodes = _rows(actor_dir / "episodes.csv")
    ret = by_episode(rows["/actor/a0/episode/return"])
    assert ret == pytest.approx({int(r["episode"]): float(r["ret"]) for r in episodes}, rel=1e-12)
    success = by_episode(rows["/actor/a0/episode/success"])
    assert success == {int(r["episode"]): float(r["success"] == "True") for r in episodes}
    assert "/task/demos" in rows and "/task/workspace" in rows
    assert any(k.startswith("/learner/") for k in rows), sorted(rows)  # live: statuses; offline: progress.csv
    if live:
        assert rows["/learner/ingested"] and rows["/actor/a0/episode/weights_version"]
    return rows


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_passage_run_recorded_and_viewed_again(tmp_path: Path) -> None:
    run_dir, rrd = tmp_path / "run", tmp_path / "live.rrd"
    up = ["up", "--scenario", "low_cov", "--method", "khgrl", "--episodes", "3", "--seed", "3", "--human-episodes",
          "1", "2", *SMALL, "--run-dir", str(run_dir), "--no-progress", "--view", f"rerun:{rrd}"]
    # (the scripted human in episodes 1 and 2: in episode 2 alone it finds nothing to correct with SMALL's networks,
    # and P_h is what is checked)
    proc = _khgrl(*up)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    live = _check_recording(rrd, run_dir, live=True)
    assert "/actor/a0/camera" not in live  # the passage world has no camera
    # the same entities from the run's records
    other = tmp_path / "other.rrd"
    proc = _khgrl("view", str(run_dir), "--out", str(other))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    offline = _check_recording(other, run_dir, live=False)
    actor = sorted(k for k in live if k.startswith("/actor/") or k.startswith("/task/"))
    assert sorted(k for k in offline if k.startswith("/actor/") or k.startswith("/task/")) == [
        k for k in actor if k != "/actor/a0/episode/weights_version"]
    # an existing recording is refused without --overwrite (and left as it was)
    before = other.stat().st_size
    proc = _khgrl("view", str(run_dir), "--out", str(other))
    assert proc.returncode == 2 and "--overwrite" in proc.stderr and other.stat().st_size == before
    proc = _khgrl(*up[:-5], "--run-dir", str(tmp_path / "run2"), "--view", f"rerun:{rrd}")
    assert proc.returncode == 2 and "--overwrite" in proc.stderr, proc.stderr
    assert not (tmp_path / "run2").exists()


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_fetch_run_recorded_with_camera(tmp_path: Path) -> None:
    pytest.importorskip("gymnasium_robotics", reason="gymnasium-robotics is a project dependency: pip install -e .")
    run_dir, rrd = tmp_path / "run", tmp_path / "fetch.rrd"
    proc = _khgrl("up", "--task", "fetch:moved", "--episodes", "2", "--human-episodes", "2", "--learning-starts", "64",
                  *SMALL, "--run-dir", str(run_dir), "--no-progress", "--view", f"rerun:{rrd}",
                  "--view-camera-every", "25")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rows = _check_recording(rrd, run_dir, live=True)
    images = rows.get("/actor/a0/camera", [])
    # Fetch's episodes are 100 steps: an image at steps 0, 25, 50, 75 of each
    assert sorted((r["episode"], r["step"]) for r in images) == [(e, t) for e in (1, 2) for t in (0, 25, 50, 75)]
    assert all(r["EncodedImage:media_type"] == ["image/jpeg"] and len(r["EncodedImage:blob"][0]) > 1000
               for r in images)
    mean = rows["/actor/a0/kmp/mean"]
    assert [len(r["LineStrips3D:strips"][0]) for r in mean] == [100, 100]  # the episode's KMP mean over its grid
