"""``khgrl demos record``: demonstrations drawn with the mouse, resampled to N steps and saved.

Unit level: :func:`khgrl.human_bridge.record.resample` and the :class:`~khgrl.human_bridge.record.Recorder` (pointer
events
and keys in, (M, N, O) out) on a fake two-view layout of a 3-D task. Window level: the real command
(:func:`~khgrl.human_bridge.record.run_record`, headless ``SDL_VIDEODRIVER=dummy``) fed with synthetic pygame events
(``pygame.event.post``) one frame at a time, under a fake clock: three demonstrations of the passage world are
drawn (a fourth is discarded with BACKSPACE), ENTER saves them, and the file is a task's demonstrations
(``load_task('passage:high_cov', demos=FILE)`` builds).
"""

from __future__ import annotations

import argparse
import functools
import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from khgrl.human_bridge.record import STRIP, add_parser, run_record  # noqa: E402
from khgrl.human_bridge.strokes import MIN_SAMPLES, Recorder, resample  # noqa: E402


@functools.lru_cache(maxsize=None)
def _passage():
    from khgrl.human_bridge.gui.task import local_descriptor

    return local_descriptor("passage:high_cov")


def _args(*argv: str) -> argparse.Namespace:
    sub = argparse.ArgumentParser(prog="khgrl demos").add_subparsers(dest="action", required=True)
    add_parser(sub)
    return sub.choices["record"].parse_args(list(argv))


class FakeLayout:
    """Two 100 x 100 pixel views side by side over [0, 1]^2: view 0 (x, y), view 1 (x, z)."""

    def view_at(self, pixel):
        x, y = pixel
        return None if not (0 <= y < 100 and 0 <= x < 200) else int(x // 100)

    def view_axes(self, k):
        return (0, 1) if k == 0 else (0, 2)

    def to_world(self, k, pixel):
        return ((pixel[0] - 100 * k) / 100.0, 1.0 - pixel[1] / 100.0)


def _ev(kind, **kw):
    return pygame.event.Event(kind, **kw)


# ------------------------------------------------------------------------------------------ unit level
def test_resample_is_linear_in_time_and_keeps_the_ends():
    v = np.array([[0.0, 1.0], [1.0, 3.0], [3.0, 7.0]])
    out = resample(v, 5, times=np.array([0.0, 0.5, 2.0]))
    np.testing.assert_allclose(out[:, 0], [0.0, 1.0, 5 / 3, 7 / 3, 3.0])
    np.testing.assert_allclose(out[:, 1], 1.0 + 2.0 * out[:, 0])
    np.testing.assert_allclose(resample(v, 3), v)  # equally spaced
    assert resample(v[:1], 4).shape == (4, 2)
    np.testing.assert_allclose(resample(v, 3, times=np.array([1.0, 1.0, 1.0])), v)  # no time span: by index


def test_recorder_strokes_in_either_view_fill_the_other_axes_from_the_reference():
    ref = np.c_[np.linspace(0, 1, 11), np.full(11, 0.25), np.linspace(0.2, 0.4, 11)]
    rec = Recorder(ref, np.zeros(3), np.ones(3), FakeLayout(), steps=21, rate=10.0)
    # view 1 (x, z): y from the reference; sampled every 0.1 s; the pointer leaving the workspace is clipped
    rec.press((110, 50), 0.0)
    for k in range(1, 10):
        rec.move((110 + 8 * k, 50 - 6 * k))
        rec.tick(0.1 * k)
    rec.move((250, -20))
    rec.release((250, -20), 1.0)
    assert len(rec.kept) == 1 and rec.done is None
    d = rec.kept[0]
    assert d.shape == (21, 3)
    np.testing.assert_allclose(d[:, 1], np.full(21, 0.25))
    np.testing.assert_allclose(d[0], [0.1, 0.25, 0.5])
    np.testing.assert_allclose(d[-1], [1.0, 0.25, 1.0])  # clipped to the workspace
    np.testing.assert_allclose(d[10], [0.1 + 0.4, 0.25, 0.5 + 0.3])  # at 0.5 s: pointer sample 5
    # view 0 (x, y): z from the reference
    rec.press((10, 90), 2.0)
    for k in range(1, 6):
        rec.move((10 + 10 * k, 90 - 10 * k))
        rec.tick(2.0 + 0.1 * k)
    rec.release((60, 40), 2.5)
    np.testing.assert_allclose(rec.kept[1][:, 2], resample(ref, 21)[:, 2])
    np.testing.assert_allclose(rec.kept[1][-1, :2], [0.6, 0.6])
    assert rec.demos().shape == (2, 21, 3)
    # a click is not a demonstration; a press outside the views does nothing
    rec.press((50, 50), 3.0)
    rec.release((50, 50), 3.0)
    rec.press((50, 150), 3.5)
    assert len(rec.kept) == 2 and rec.stroke is None and "too short" in rec.message


def test_recorder_keys_and_speed_limit():
    ref = np.c_[np.linspace(0, 1, 11), np.full(11, 0.5)]
    rec = Recorder(ref, np.zeros(2), np.ones(2), FakeLayout(), rate=100.0, speed=0.5, limit=2)
    assert rec.steps == 11
    rec.key(pygame.K_RETURN)
    assert rec.done is None and "nothing to save" in rec.message
    rec.press((0, 50), 0.0)
    rec.move((100, 50))  # x: 0 -> 1 (clipped to the workspace, 1.0)
    for k in range(1, 11):
        rec.tick(0.1 * k)
    assert rec.pen[0] == pytest.approx(0.5)  # 1 s at 0.5 units/s
    rec.key(pygame.K_BACKSPACE)  # discards the stroke being drawn
    assert rec.stroke is None and not rec.kept
    for n in range(2):
        rec.press((0, 50), 10.0 * n)
        for k in range(1, MIN_SAMPLES + 1):
            rec.move((20 * k, 50))
            rec.tick(10.0 * n + 0.01 * k)
        rec.release((20 * MIN_SAMPLES, 50), 10.0 * n + 0.06)
        if n == 0:
            rec.key(pygame.K_BACKSPACE)  # discards the last kept one
            assert not rec.kept
    assert len(rec.kept) == 1 and rec.done is None
    rec.press((0, 50), 20.0)
    for k in range(1, MIN_SAMPLES + 1):
        rec.tick(20.0 + 0.01 * k)
    rec.release((0, 50), 20.1)
    assert rec.done == "save"  # the limit (--demos-per 2) reached
    rec.done = None
    rec.key(pygame.K_ESCAPE)
    assert rec.done == "quit"
    with pytest.raises(ValueError):
        Recorder(ref, np.zeros(2), np.ones(2), FakeLayout(), rate=0.0)


def test_bad_arguments_exit_2_with_one_line(tmp_path, capsys):
    existing = tmp_path / "d.npz"
    existing.write_bytes(b"x")
    assert run_record(_args("--out", str(existing))) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"khgrl demos record: --out {existing} exists (use --overwrite to replace it)"]
    assert run_record(_args("--out", str(tmp_path / "d.txt"))) == 2
    assert "use a .npz or .csv" in capsys.readouterr().err
    assert run_record(_args("--out", str(tmp_path / "e.npz"), "--task", "no_such_module:make")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot import" in err[0]


# ------------------------------------------------------------------------------------------ the window
def _script(renderer_of, strokes, keys_between=None):
    """Per-frame event batches: each stroke is DOWN, MOTION..., MOTION + UP at pixels of view 0 (one pen sample a
    frame), optionally a key after it; then ENTER."""
    frames: list[list] = [[]]  # one empty frame: the window settles

    def pix(p):
        return tuple(int(round(c)) for c in renderer_of().to_pixel(0, p))

    for i, pts in enumerate(strokes):
        frames.append([_ev(pygame.MOUSEBUTTONDOWN, pos=pix(pts[0]), button=1)])
        frames += [[_ev(pygame.MOUSEMOTION, pos=pix(p), rel=(1, 0), buttons=(1, 0, 0))] for p in pts[1:]]
        frames[-1].append(_ev(pygame.MOUSEBUTTONUP, pos=pix(pts[-1]), button=1))  # with the last sample
        if keys_between and i in keys_between:
            frames.append([_ev(pygame.KEYDOWN, key=keys_between[i], mod=0, unicode="")])
    frames.append([_ev(pygame.KEYDOWN, key=pygame.K_RETURN, mod=0, unicode="\r")])
    return frames


def test_record_three_demos_through_the_window_and_train_from_them(tmp_path):
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.demos import load_demos
    from khgrl.common.tasks.render import TaskRenderer
    from khgrl.common.tasks.world import build_task_world

    d = _passage()
    out = tmp_path / "mine.csv"
    args = _args("--task", "passage:high_cov", "--out", str(out), "--steps", "120", "--size", "400")
    ren = TaskRenderer(d, size=(400, 400 + STRIP), strip_height=STRIP)  # the window's layout: to aim the pointer
    idx = np.linspace(0, d.horizon - 1, 60).astype(int)
    lifts = (0.0, 0.03, -0.03, 0.05)
    strokes = [d.mean[idx] + np.array([0.0, dy]) for dy in lifts]
    frames = iter(_script(lambda: ren, strokes, keys_between={3: pygame.K_BACKSPACE}))
    clock = iter(0.02 * np.arange(10_000))

    def events():
        for e in next(frames, [_ev(pygame.QUIT)]):
            pygame.event.post(e)
        return pygame.event.get()

    assert run_record(args, clock=lambda: float(next(clock)), events=events) == 0
    demos = load_demos(out)
    assert demos.shape == (3, 120, 2)
    ref = resample(d.mean[idx], 120)
    for k, dy in enumerate(lifts[:3]):
        np.testing.assert_allclose(demos[k], ref + np.array([0.0, dy]), atol=0.006)  # a pixel is ~0.0027
    world = build_task_world(load_task("passage:high_cov", demos=out))
    assert world.demos.shape == (3, 120, 2) and np.all(np.isfinite(world.model.grid_mean))
    # the file is never overwritten without --overwrite; ESC quits without saving
    frames = iter([[_ev(pygame.KEYDOWN, key=pygame.K_ESCAPE, mod=0, unicode="\x1b")]])
    assert run_record(_args("--out", str(out), "--steps", "120"), events=events) == 2
    assert run_record(_args("--out", str(out), "--steps", "120", "--overwrite"), events=events) == 1
    np.testing.assert_allclose(load_demos(out), demos)
    _train_from(out, tmp_path / "run", demos)


def _train_from(path, run_dir, demos) -> None:
    """``khgrl up --demos FILE``: the run trains on the recorded demonstrations (horizon 120) and keeps a copy."""
    import json
    import os
    import subprocess
    import sys

    from helpers import REPO, SMALL

    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error"}
    proc = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "up", "--demos", str(path), "--episodes", "2",
                           "--method", "kgrl", "--learning-starts", "32", "--run-dir", str(run_dir), "--no-progress",
                           *SMALL], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    config = json.loads((run_dir / "config.json").read_text())
    kept = run_dir / "demos.csv"
    assert config["demos"] == str(kept.resolve())
    from khgrl.common.tasks.demos import load_demos

    np.testing.assert_allclose(load_demos(kept), demos)
    episodes = json.loads((run_dir / "actor-a0" / "episodes.json").read_text())
    assert len(episodes) == 2 and all(e["steps"] <= 120 for e in episodes)
    state = json.loads((run_dir / "learner" / "checkpoint" / "state.json").read_text())
    assert state["total_ingested"] == sum(e["steps"] for e in episodes) and state["iterations"] > 0


def test_without_a_display_exit_3(tmp_path, monkeypatch, capsys):
    for k in ("SDL_VIDEODRIVER", "DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(k, raising=False)
    assert run_record(_args("--out", str(tmp_path / "x.npz"))) == 3
    assert "no display" in capsys.readouterr().err


def test_a_task_without_demonstrations_gets_a_placeholder_from_start_to_goal(tmp_path):
    from khgrl.common.tasks.api import TaskError, task_demos
    from khgrl.common.tasks.passage.task import make_task
    from khgrl.common.tasks.world import build_task_world
    from khgrl.human_bridge.record import placeholder_demos

    task = make_task("high_cov").with_demos(tmp_path / "not-yet.npz")
    with pytest.raises(TaskError):
        task_demos(task)
    demos = placeholder_demos(task, 50)
    assert demos.shape == (2, 50, 2)
    sc = task.make_env(0).scenario
    np.testing.assert_allclose(demos.mean(axis=0)[[0, -1]], [sc.start, sc.goal])
    world = build_task_world(task.with_demos(demos))
    np.testing.assert_allclose(world.model.grid_mean[[0, -1]], [sc.start, sc.goal], atol=0.02)
