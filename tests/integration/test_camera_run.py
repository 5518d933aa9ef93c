"""Camera tasks through the real system (issue 37).

The passage world observed as a state vector and a 16 x 16 image (deploy/examples/camera_task.py): ``khgrl up``
runs it to the end; the actor's batches carry frames, the learner's TQC with DrQ's image policy stores exactly what
the actor sent, each step once, and each frame once (the replay's live frames: one per stored transition and one
per episode, plus a stream's pin); people see the frames (Rerun, ``khgrl view``, LeRobot export).

gym-hil's Panda from its two 128 x 128 cameras (``panda:pick-pixels``): a learner SIGKILLed after a full checkpoint
with batches in its journal and ``--resume``d, on Zenoh's shared memory: nothing lost, nothing twice, the frames
still stored once."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import REPO, ProcGroup, read_json, unique_run, wait_for

CAMERA = "khgrl.deploy.examples.camera_task:make_task"
UP = [sys.executable, "-m", "khgrl.deploy.cli", "up"]
SMALL = ["--net-arch", "64", "64", "--batch-size", "32", "--learning-starts", "32", "--buffer-size", "5000",
         "--gradient-steps", "2"]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RUST_LOG", "error")
    return env


def _replay(ckpt_dir: Path):
    """The learner's replay buffer in its checkpoint (its own file, written by this test's run)."""
    from khgrl.learner.checkpoint import find_checkpoint
    from stable_baselines3.common.save_util import load_from_pkl

    return load_from_pkl(find_checkpoint(ckpt_dir) / "replay_buffer.pkl")


def _episodes(run_dir: Path) -> int:
    return len((run_dir / "actor-a0" / "episodes.csv").read_text().strip().splitlines()) - 1


def _steps(run_dir: Path) -> list[int]:
    rows = (run_dir / "actor-a0" / "episodes.csv").read_text().strip().splitlines()[1:]
    return [int(r.split(",")[1]) for r in rows]


def _assert_frames_once(rb, n: int, episodes: int) -> None:
    """Every stored transition's frames alive, each frame once: n transitions of ``episodes`` episodes hold
    n + episodes frames (+1: a stream's pin after a batch that did not end its episode)."""
    from khgrl.learner.frame_replay import FrameReplayBuffer

    assert isinstance(rb, FrameReplayBuffer) and rb.pos == n
    assert np.all(rb.obs_frame[:n] >= 0) and np.all(rb.next_frame[:n] >= 0)
    assert n + episodes <= rb.store.live <= n + episodes + 1, (rb.store.live, n, episodes)
    held = np.concatenate([rb.obs_frame[:n], rb.next_frame[:n], [p[0] for p in rb.pins.values()]]).astype(int)
    assert len(np.unique(held)) == rb.store.live  # no frame alive that no slot or pin holds


@pytest.mark.integration
@pytest.mark.timeout(180)
def test_camera_task_through_khgrl_up(tmp_path: Path) -> None:
    from khgrl.benchmarks.scale import provenance_check

    run_dir, rrd = tmp_path / "run", tmp_path / "live.rrd"
    proc = subprocess.run([*UP, "--task", CAMERA, "--human", "none", "--episodes", "2", *SMALL, "--run-dir",
                           str(run_dir), "--no-progress", "--view", f"rerun:{rrd}", "--view-camera-every", "5"],
                          cwd=REPO, env=_env(), capture_output=True, text=True, timeout=150)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = read_json(run_dir / "summary.json")
    actor = read_json(run_dir / "actor-a0" / "summary.json")
    n = actor["transitions"]
    assert actor["episodes"] == 2 and actor["unconfirmed_transitions"] == 0 and actor["rejects"] == {}
    assert summary["a0"]["transitions"] == n == actor["sent"] > 0
    state = read_json(run_dir / "learner" / "checkpoint" / "state.json")
    assert state["total_ingested"] == n
    check = provenance_check(run_dir)
    assert check["lost"] == 0 and check["duplicated"] == 0 and check["produced"] == n, check
    rb = _replay(run_dir / "learner")
    _assert_frames_once(rb, n, _episodes(run_dir))
    assert rb.store.shapes == {"cam": (3, 16, 16)}  # channel-first, as SB3 holds the model's images
    assert "task passage-camera" in (run_dir / "learner" / "learner.log").read_text()
    for path, steps in zip(sorted((run_dir / "actor-a0" / "steps").glob("episode-*.npz")), _steps(run_dir)):
        with np.load(path, allow_pickle=False) as z:  # the step records keep the state and, apart, the images
            assert z["obs"].shape == (steps, 5) and z["final_obs"].shape == (5,)
            assert z["image/cam"].shape == (steps, 16, 16, 3) and z["image/cam"].dtype == np.uint8
    _people_see_the_frames(run_dir, rrd, tmp_path)


def _people_see_the_frames(run_dir: Path, live_rrd: Path, tmp_path: Path) -> None:
    """The policy's images in the live Rerun view (every 5th step), in ``khgrl view`` (every step) and in
    ``khgrl export --lerobot`` as ``observation.images.cam``, read back by LeRobot's own loader and by
    ``--demos lerobot:``."""
    from khgrl.common.lerobot.demos import load_lerobot_demos
    from khgrl.common.step_records import images_of, read_steps

    from lerobot_data import load_with_library
    from rrd_read import read_rrd

    steps = _steps(run_dir)
    frames = [images_of(r)["cam"] for r in read_steps(run_dir / "actor-a0")]
    assert [len(f) for f in frames] == steps and all(f.max() == 255 for f in frames)  # the robot's white dot
    _, live = read_rrd(live_rrd)
    assert sorted((r["episode"], r["step"]) for r in live["/actor/a0/images/cam"]) == \
        [(e + 1, t) for e, n in enumerate(steps) for t in range(0, n, 5)]
    rrd = tmp_path / "view.rrd"
    view = subprocess.run([*UP[:-1], "view", str(run_dir), "--out", str(rrd)], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=120)
    assert view.returncode == 0, view.stdout + view.stderr
    assert len(read_rrd(rrd)[1]["/actor/a0/images/cam"]) == sum(steps)
    out = tmp_path / "export"
    export = subprocess.run([*UP[:-1], "export", str(run_dir), "--lerobot", str(out)], cwd=REPO, env=_env(),
                            capture_output=True, text=True, timeout=120)
    assert export.returncode == 0, export.stdout + export.stderr
    ds = load_with_library(out)
    assert ds.meta.features["observation.images.cam"]["shape"] == (16, 16, 3)
    for k in (0, steps[0] - 1, steps[0], sum(steps) - 1):  # first and last frames of both episodes
        e, i = (0, k) if k < steps[0] else (1, k - steps[0])
        image = ds[k]["observation.images.cam"].numpy()  # (C, H, W) floats in [0, 1], as LeRobot gives images
        np.testing.assert_array_equal(np.rint(image.transpose(1, 2, 0) * 255).astype(np.uint8), frames[e][i])
    # the export, images and all, is demonstrations for a next run (the position: the state's first 2 numbers)
    demos = load_lerobot_demos(f"lerobot:{out}?feature=observation.state&dims=0:2")
    states = [r["obs"][:, :2] for r in read_steps(run_dir / "actor-a0")]
    assert demos.shape[0] == 2 and demos.shape[2] == 2
    np.testing.assert_allclose(demos[:, 0], [s[0] for s in states], atol=1e-6)


def _journal_rows(ckpt_dir: Path) -> int:
    from khgrl.learner.journal_scan import read_records

    state_file = ckpt_dir / "checkpoint" / "state.json"
    if not state_file.exists():
        return 0
    return sum(m.n for m in read_records(ckpt_dir / "journal", read_json(state_file)["journal"]["next"]))


def _new_pools(since: float) -> list[Path]:
    """Zenoh shared-memory pools (``/dev/shm/*.zenoh`` of 1 MiB or more) made since ``since``."""
    found = []
    for f in Path("/dev/shm").glob("*.zenoh"):
        try:
            st = f.stat()
        except FileNotFoundError:  # a stale segment another Zenoh process cleaned up meanwhile
            continue
        if st.st_ctime >= since and st.st_size >= 2**20:
            found.append(f)
    return found


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_panda_pixels_learner_killed_and_resumed_loses_nothing(tmp_path: Path, monkeypatch) -> None:
    """On Zenoh's shared memory (deploy/zenoh/shared-memory.json5, every process through ``ZENOH_CONFIG``): the
    frames' path that ``khgrl bench images`` measures; every other test runs on KhGRL's default (copies). Two
    episodes of ``panda:pick-pixels`` (about 100 steps, two 128 x 128 frames each); the learner is killed once it
    has a full checkpoint and batches in its journal after it."""
    pytest.importorskip("gym_hil", reason="gym-hil is a project dependency: pip install -e .")
    from khgrl.benchmarks.scale import provenance_check

    monkeypatch.setenv("ZENOH_CONFIG", str(REPO / "deploy" / "zenoh" / "shared-memory.json5"))
    t0 = time.time() - 1.0
    learner_args = ["--learning-starts", "16", "--max-lead", "8", "--checkpoint-every", "32", "--buffer-size", "2000",
                    "--batch-size", "16", "--gradient-steps", "1"]
    actor_args = ["--task", "panda:pick-pixels", "--method", "kgrl", "--learning-starts", "16", "--max-lead", "8",
                  "--episodes", "2", "--id", "a0", "--flush-timeout", "120"]
    run, run_dir = unique_run("pix"), tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, *learner_args)
        actor = g.actor(run, ep, *actor_args)
        wait_for(lambda: _journal_rows(run_dir / "learner") >= 16, 240, "a full checkpoint, then the journal",
                 procs=[learner, actor])
        assert _new_pools(t0), "no process of this run put its batches on shared memory"
        learner.kill()
        learner.wait(30)
        resumed = g.learner(run, ep, *learner_args, "--resume")
        assert actor.wait(240) == 0, actor.tail()
        assert resumed.stop(60) == 0, resumed.text()[-3000:]
        log = resumed.text()
    assert "journal: replayed" in log, log[-3000:]
    assert "task panda-pick-pixels" in log, log[-3000:]
    summary = read_json(run_dir / "actor-a0" / "summary.json")
    assert summary["episodes"] == 2 and summary["unconfirmed_transitions"] == 0, summary
    check = provenance_check(run_dir)
    assert check["lost"] == 0 and check["duplicated"] == 0 and check["produced"] == summary["next_index"], check
    rb = _replay(run_dir / "learner")
    _assert_frames_once(rb, summary["next_index"], _episodes(run_dir))
    assert rb.store.shapes == {"front": (3, 128, 128), "wrist": (3, 128, 128)}  # channel-first, as SB3 holds them
    assert {k: f.dtype for k, f in rb.store.frames.items()} == {"front": np.uint8, "wrist": np.uint8}
