"""LeRobot datasets through the real system: a dataset written by LeRobot's own writer from the 3-D example task's
demonstrations (episodes of 6 lengths) drives ``khgrl up --demos lerobot:...``, whose KMP is fitted on them
resampled; ``khgrl export`` writes that run (with the scripted human's corrections) back as a LeRobot dataset, read
with LeRobot's own loader and checked frame by frame against the run's records."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from khgrl.deploy.examples.own_task import make_demos

from helpers import REPO, read_json
from lerobot_data import load_with_library, write_state_dataset

OWN = "khgrl.deploy.examples.own_task:make_task"
CLI = [sys.executable, "-m", "khgrl.deploy.cli"]
LENGTHS = (60, 90, 120, 150, 180, 200)  # frames of the 6 episodes; the task's N is 200


def _env() -> dict:
    return {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error"}


def _csv(path: Path) -> list[dict]:
    with open(path) as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, str]:
    """A run of the own task on LeRobot demonstrations: 2 episodes, the scripted human lifts it in episode 2."""
    base = tmp_path_factory.mktemp("lerobot")
    # demonstration k at F_k frames (the same path, sampled coarser), behind a first column the run must skip
    episodes = [np.concatenate([np.full((f, 1), 7.0), make_demos(n=f)[k]], axis=1) for k, f in enumerate(LENGTHS)]
    spec = f"lerobot:{write_state_dataset(base / 'demos', episodes, task='own task')}?dims=1:4"
    run_dir = base / "run"
    proc = subprocess.run([*CLI, "up", "--task", OWN, "--demos", spec, "--episodes", "2", "--human-episodes", "2",
                           "--learning-starts", "64", "--run-dir", str(run_dir), "--no-progress"], cwd=REPO,
                          env=_env(), capture_output=True, text=True, timeout=360)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return run_dir, spec


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_khgrl_up_trains_on_lerobot_demos(run: tuple[Path, str]) -> None:
    from khgrl.common.step_records import read_steps
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    run_dir, spec = run
    with np.load(run_dir / "demos.npz") as kept:  # what every process read: the episodes resampled to N = 200
        demos, source = kept["demos"], str(kept["source"])
    assert source.startswith("lerobot:/") and source.endswith("?feature=observation.state&dims=1:4")
    assert read_json(run_dir / "config.json")["demos"] == str((run_dir / "demos.npz").resolve())
    original = make_demos()
    assert demos.shape == original.shape == (6, 200, 3)
    for m, frames in enumerate(LENGTHS):  # linear interpolation of a smooth path: error ~ h^2, h = 1 / (F - 1)
        err = np.abs(demos[m] - original[m]).max()
        assert err < 2.0 / (frames - 1) ** 2 + 1e-6, (frames, err)
    assert np.abs(demos[0] - original[0]).max() > 1e-6  # the 60-frame episode was resampled, not copied
    rows = _csv(run_dir / "actor-a0" / "episodes.csv")
    assert read_json(run_dir / "learner" / "checkpoint" / "state.json")["total_ingested"] == \
        sum(int(r["steps"]) for r in rows) > 0
    # the actor's KMP is the one fitted on these demonstrations, close to the one of the originals
    kmp = read_steps(run_dir / "actor-a0")[0]["kmp_mean"]
    own = KGRLEnv(load_task(OWN)).mapping.model.grid_mean
    mine = KGRLEnv(load_task(OWN, run_dir / "demos.npz")).mapping.model.grid_mean
    np.testing.assert_allclose(kmp, mine, atol=1e-9)
    np.testing.assert_allclose(kmp, own, atol=2e-3)


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_export_reads_back_with_lerobots_loader(run: tuple[Path, str], tmp_path: Path) -> None:
    from khgrl.common.step_records import read_steps

    run_dir, _ = run
    out = tmp_path / "export"
    proc = subprocess.run([*CLI, "export", str(run_dir), "--lerobot", str(out)], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    ds = load_with_library(out)
    rows = _csv(run_dir / "actor-a0" / "episodes.csv")
    records = read_steps(run_dir / "actor-a0")
    assert ds.num_episodes == len(rows) == len(records) == 2
    assert ds.num_frames == sum(int(r["steps"]) for r in rows)
    assert ds.fps == 10 and ds.meta.tasks.index.tolist() == [OWN]
    data = ds.hf_dataset.with_format("numpy")
    episode = np.asarray(data["episode_index"])
    corrected = {(int(r["episode"]), int(r["step"])) for r in _csv(run_dir / "actor-a0" / "corrections.csv")}
    assert corrected, "the scripted human corrected nothing"
    for k, rec in enumerate(records):
        at = np.flatnonzero(episode == k)
        assert np.array_equal(np.asarray(data["frame_index"])[at], np.arange(len(rec["t"])))
        flags = np.asarray(data["complementary_info.is_intervention"])[at].astype(bool)
        assert np.array_equal(flags, rec["intervened"])
        assert {(int(rec["episode"]), int(t)) for t in rec["t"][flags]} == \
            {c for c in corrected if c[0] == int(rec["episode"])}
        assert flags.sum() == int(rows[k]["intervention_steps"])
        np.testing.assert_array_equal(np.stack(data["action"][at]), rec["action"])
        np.testing.assert_array_equal(np.stack(data["observation.state"][at]), rec["obs"])
        np.testing.assert_allclose(np.asarray(data["next.reward"])[at], rec["reward"], rtol=1e-6, atol=1e-4)
        done = np.asarray(data["next.done"])[at].astype(bool)
        assert done[-1] and not done[:-1].any()
        valid = np.asarray(data["complementary_info.human_position_valid"])[at].astype(bool)
        assert np.array_equal(valid, np.isfinite(rec["p_h"]).all(axis=1))
        np.testing.assert_allclose(np.stack(data["complementary_info.human_position"][at])[valid],
                                   rec["p_h"][valid], atol=1e-6)
    prov = json.loads((out / "meta" / "khgrl.json").read_text())
    assert prov["run"] == read_json(run_dir / "config.json")["runtime"]["run"]
    assert [(e["actor"], e["episode"]) for e in prov["episodes"]] == [("a0", 1), ("a0", 2)]

    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    again = subprocess.run([*CLI, "export", str(run_dir), "--lerobot", str(out)], cwd=REPO, env=_env(),
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "exists: give --overwrite" in again.stderr
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    forced = subprocess.run([*CLI, "export", str(run_dir), "--lerobot", str(out), "--overwrite", "--fps", "20"],
                            cwd=REPO, env=_env(), capture_output=True, text=True, timeout=120)
    assert forced.returncode == 0, forced.stderr
    assert load_with_library(out).fps == 20 and not list(tmp_path.glob(".export.*"))  # no temporary folder left


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_export_overwrite_replaces_only_a_dataset_it_wrote(run: tuple[Path, str], tmp_path: Path) -> None:
    """Issue 33, defect 8. Before the fix ``--overwrite`` deleted whatever OUT was: the source run, the folder of
    runs that holds it (``--lerobot runs --overwrite``), the LeRobot demonstrations the run was trained on, a dataset
    folder holding a file of the user's."""
    run_dir, _ = run
    before = _tree(run_dir.parent)
    out = tmp_path / "mine"
    assert _export(run_dir, out).returncode == 0
    (out / "notes.txt").write_text("mine")
    for target, why in ((run_dir, "is (or holds) the run"), (run_dir.parent, "is (or holds) the run"),
                        (run_dir.parent / "demos", "no meta/khgrl.json"), (out, "holds notes.txt")):
        refused = _export(run_dir, target, "--overwrite")
        assert refused.returncode == 2 and why in refused.stderr and "not replaced" in refused.stderr, refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    assert _tree(run_dir.parent) == before and (out / "notes.txt").read_text() == "mine"


def _export(run_dir: Path, out: Path, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, "export", str(run_dir), "--lerobot", str(out), *flags], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=120)


def _tree(path: Path) -> dict:
    return {str(p.relative_to(path)): p.stat().st_size for p in sorted(path.rglob("*")) if p.is_file()}
