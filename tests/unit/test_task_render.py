"""Headless tests of the task renderer (common/tasks/render.py) and the KMP plot for O >= 3 (common/kmp/plots.py)."""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import time  # noqa: E402

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from gymnasium import spaces  # noqa: E402
from khgrl.common.kmp.fit import KMPConfig, fit_model  # noqa: E402
from khgrl.common.kmp.plots import plot_kmp  # noqa: E402
from khgrl.common.tasks.api import Cuboid, Point, Sphere, Task, View  # noqa: E402
from khgrl.common.tasks.kgrl_env import KGRLEnv  # noqa: E402
from khgrl.common.tasks.passage.env import PassageEnv  # noqa: E402
from khgrl.common.tasks.render import TaskFrame, TaskRenderer, frame_from_env, nice_ticks, view_extent  # noqa: E402
from khgrl.common.wire.descriptor import TaskDescriptor  # noqa: E402

N = 60


class PointRobot3D(gym.Env):
    """Action = desired position (3,); the robot moves toward it at most 0.03 per step; observation = robot."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(-1.0, 2.0, shape=(3,), dtype=np.float64)
        self.action_space = spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float64)
        self.robot = np.full(3, 0.1)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.robot = np.full(3, 0.1)
        return self.robot.copy(), {}

    def step(self, action):
        d = np.asarray(action, np.float64) - self.robot
        dist = float(np.linalg.norm(d))
        self.robot = self.robot + (d if dist <= 0.03 else d * 0.03 / dist)
        done = bool(np.linalg.norm(self.robot - np.array([0.9, 0.9, 0.5])) < 0.03)
        return self.robot.copy(), 0.0, done, False, {"success": done}


def _demos3() -> np.ndarray:
    s = np.linspace(0.0, 1.0, N)[:, None]
    start, goal = np.array([0.1, 0.1, 0.1]), np.array([0.9, 0.9, 0.5])
    out = []
    for k in range(4):
        bump = np.sin(np.pi * s) * np.array([0.05 * (k - 1.5), -0.05 * (k - 1.5), 0.15 + 0.05 * k])
        out.append(start + (goal - start) * s + bump)
    return np.stack(out)


def _task3() -> Task:
    view = View(axes=(0, 1), third=2, names=("x", "y", "z"),
                shapes=(Cuboid("keep-out", (0.4, 0.4, 0.0), (0.6, 0.6, 0.3)), Sphere("ball", (0.2, 0.7, 0.5), 0.08),
                        Point("start", (0.1, 0.1, 0.1)), Point("goal", (0.9, 0.9, 0.5))))
    return Task(name="point3d", make_env=lambda seed: PointRobot3D(), demos=_demos3(),
                workspace=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), kmp=KMPConfig(n_components=4), default_scale=0.5,
                position=lambda obs: obs, view=view)


@pytest.fixture(scope="module")
def passage() -> tuple[PassageEnv, TaskDescriptor]:
    env = PassageEnv("high_cov")
    return env, env.descriptor("passage:high_cov")


@pytest.fixture(scope="module")
def env3() -> KGRLEnv:
    return KGRLEnv(_task3(), seed=0)


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.any(a != b, axis=2)


# ---------------------------------------------------------------------------- 2-D: passage
def test_passage_image_size_and_robot_pixels(passage) -> None:
    _, d = passage
    r = TaskRenderer(d, size=(640, 480), strip_height=50)
    assert len(r.views) == 1 and r.view_axes(0) == (0, 1)
    p, q = np.array([0.85, 0.12]), np.array([0.2, 0.85])
    img_p = r.render_rgb(TaskFrame(position=p, desired=p, text=["hello"]))
    img_q = r.render_rgb(TaskFrame(position=q, desired=q, text=["hello"]))
    assert img_p.shape == (480, 640, 3) and img_p.dtype == np.uint8
    diff = _changed(img_p, img_q)
    for pt in (p, q):  # the images differ at the robot's pixel and not far from it
        x, y = np.rint(r.to_pixel(0, pt)).astype(int)
        assert diff[y, x]
    ys, xs = np.nonzero(diff)
    near = [min(np.hypot(x - c[0], y - c[1]) for c in (r.to_pixel(0, p), r.to_pixel(0, q))) for x, y in zip(xs, ys)]
    assert max(near) < 20
    x, y = np.rint(r.to_pixel(0, p)).astype(int)
    red, green, blue = img_p[y, x].astype(int)
    assert red > green + 50 and blue > green + 50  # robot purple


def test_passage_draw_matches_render_rgb_and_band_changes_pixels(passage) -> None:
    env, d = passage
    r = TaskRenderer(d, size=(500, 400))
    env.reset()
    for _ in range(30):
        env.step(np.zeros(2))
    f = frame_from_env(env)
    assert f.band is not None and f.band.shape == (d.horizon, 2, 2)
    assert f.trail.shape == (31, 2) and f.t == 30 and not f.human_active
    img = r.render_rgb(f)
    surf = pygame.Surface((500, 400))
    r.draw(surf, f)
    ref = np.frombuffer(pygame.image.tobytes(surf, "RGB"), np.uint8).reshape(400, 500, 3)
    np.testing.assert_array_equal(img, ref)
    assert _changed(img, r.render_rgb(f, show_band=False)).sum() > 500


def test_correction_frame_from_env(passage) -> None:
    env, d = passage
    env.reset()
    env.set_correction(np.array([0.4, 0.7]))
    env.step(np.zeros(2))
    f = frame_from_env(env)
    env.set_correction(None)
    assert f.human_active and np.allclose(f.correction, [0.4, 0.7])
    r = TaskRenderer(d, size=(400, 360))
    img = r.render_rgb(f)
    x, y = np.rint(r.to_pixel(0, f.correction)).astype(int)
    assert max(img[y, x]) < 60  # the black cross of P_h
    rect = r.views[0].rect
    assert tuple(img[rect.top + 1, rect.centerx]) == (255, 140, 0)  # the orange "human" frame


# ---------------------------------------------------------------------------- 3-D task
def test_3d_two_views_and_robot_pixels(env3: KGRLEnv) -> None:
    d = env3.descriptor("tests:point3d")
    assert d.out_dim == 3 and d.third == 2
    r = TaskRenderer(d, size=(800, 420))
    assert [r.view_axes(k) for k in range(2)] == [(0, 1), (0, 2)]
    assert r.views[0].rect.right <= r.views[1].rect.left
    a, b = np.array([0.2, 0.3, 0.8]), np.array([0.8, 0.3, 0.8])
    img_a, img_b = r.render_rgb(TaskFrame(position=a, desired=a)), r.render_rgb(TaskFrame(position=b, desired=b))
    assert img_a.shape == (420, 800, 3)
    diff = _changed(img_a, img_b)
    for k in range(2):
        for p in (a, b):
            x, y = np.rint(r.to_pixel(k, p)).astype(int)
            assert r.views[k].rect.collidepoint(x, y) and diff[y, x]
    # only the z coordinate moves: view 0 (x, y) is unchanged, view 1 (x, z) changes
    c = a + np.array([0.0, 0.0, -0.6])
    diff_z = _changed(img_a, r.render_rgb(TaskFrame(position=c, desired=c)))
    assert not diff_z[r.views[0].rect.top:r.views[0].rect.bottom, r.views[0].rect.left:r.views[0].rect.right].any()
    assert diff_z[r.views[1].rect.top:r.views[1].rect.bottom, r.views[1].rect.left:r.views[1].rect.right].any()


def test_3d_frame_from_env_after_steps(env3: KGRLEnv) -> None:
    env3.reset(seed=1)
    for _ in range(10):
        env3.step(np.zeros(3))
    f = frame_from_env(env3, text=["x"])
    assert f.position.shape == (3,) and f.trail.shape == (11, 3) and f.band.shape == (N, 2, 3) and f.text == ["x"]
    r = TaskRenderer(env3.descriptor(), size=(600, 300), strip_height=0)
    img = r.render_rgb(f)
    assert img.shape == (300, 600, 3)
    assert _changed(img, r.render_rgb(f, show_demos=False, show_mean=False, show_band=False)).any()


def test_pixel_world_round_trip(env3: KGRLEnv, passage) -> None:
    rng = np.random.default_rng(0)
    for d in (env3.descriptor(), passage[1]):
        r = TaskRenderer(d, size=(700, 450))
        pts = rng.uniform(d.workspace_low, d.workspace_high, size=(50, d.out_dim))
        for k, v in enumerate(r.views):
            px = r.to_pixel(k, pts)
            assert px.shape == (50, 2)
            back = np.array([r.to_world(k, q) for q in px])
            np.testing.assert_allclose(back, pts[:, list(v.axes)], atol=1e-9)
            assert all(r.view_at(q) == k for q in px)
            full = r.point_at(k, px[0], base=np.zeros(d.out_dim))
            np.testing.assert_allclose(full[list(v.axes)], pts[0, list(v.axes)], atol=1e-9)
            other = [i for i in range(d.out_dim) if i not in v.axes]
            assert np.all(full[other] == 0.0)
        lo = r.to_pixel(0, np.asarray(d.workspace_low))
        hi = r.to_pixel(0, np.asarray(d.workspace_high))
        assert hi[0] > lo[0] and hi[1] < lo[1]  # x right, y up
    assert r.view_at((r.width - 1, r.height - 1)) is None  # the text strip


def test_axes_scaled_to_workspace() -> None:
    d = KGRLEnv(_task3()).descriptor()
    big = TaskDescriptor(**{**d.__dict__, "workspace_low": (-5.0, -5.0, 0.0), "workspace_high": (15.0, 15.0, 2.0),
                            "shapes": ()})
    lo, hi = view_extent(big)
    assert np.allclose(lo, [-5.6, -5.6, -0.06]) and np.allclose(hi, [15.6, 15.6, 2.06])
    r = TaskRenderer(big, size=(800, 400))
    v = r.views[1]  # x spans 20, z spans 2: more than 4:1, so stretched to the view
    assert np.allclose(v.lo, [-5.6, -0.06]) and np.allclose(v.hi, [15.6, 2.06])
    assert list(nice_ticks(0.0, 1.0)) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert list(nice_ticks(-5.6, 15.6)) == [-5.0, 0.0, 5.0, 10.0, 15.0]


def test_render_is_fast_enough_for_50hz(passage) -> None:
    env, d = passage
    r = TaskRenderer(d, size=(800, 600))
    env.reset()
    f = frame_from_env(env)
    r.render_rgb(f)
    t0 = time.perf_counter()
    for _ in range(20):
        r.render_rgb(f)
    assert (time.perf_counter() - t0) / 20 < 0.02


def test_too_small_size_is_refused(passage) -> None:
    with pytest.raises(ValueError, match="too small"):
        TaskRenderer(passage[1], size=(100, 100))


# ---------------------------------------------------------------------------- kmp fit plot, O = 3
def test_plot_kmp_o3_writes_png(tmp_path) -> None:
    demos = _demos3()
    model, ref = fit_model(demos, KMPConfig(n_components=4))
    out = plot_kmp(model, ref, demos, tmp_path / "k3.png", title="o3", names=("x", "y", "z"))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 5000


def test_plot_kmp_o1_without_reference(tmp_path) -> None:
    demos = _demos3()[:, :, 2:]
    model, _ = fit_model(demos, KMPConfig(n_components=3))
    out = plot_kmp(model, None, demos, tmp_path / "k1.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_kmp_fit_o3(tmp_path, capsys) -> None:
    from khgrl.common.tasks.demos import save_demos
    from khgrl.deploy.cli import main

    src = tmp_path / "d3.npz"
    save_demos(src, _demos3())
    png = tmp_path / "fit3.png"
    assert main(["kmp", "fit", str(src), "--out", str(png), "--components", "4", "--box", "-0.5", "1.5"]) == 0
    assert str(png) in capsys.readouterr().out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000


def test_a_table_under_the_task_does_not_hide_the_object_seen_from_above() -> None:
    """Fetch's table (below every demonstration in z) is drawn faintly in the top view, where the moved object
    lies on it; in the side view it is the solid obstacle it is."""
    from khgrl.common.tasks.fetch.task import DEMO_OBJECT, MOVE, make_task

    env = KGRLEnv(make_task("moved"))
    r = TaskRenderer(env.descriptor("fetch:moved"), size=(800, 420))
    start = np.asarray(env.descriptor("fetch:moved").mean)[0]
    img = r.render_rgb(TaskFrame(position=start, desired=start))
    obj = DEMO_OBJECT + MOVE
    x, y = np.rint(r.to_pixel(0, obj)).astype(int)
    assert img[y, x, 0] > img[y, x, 2] + 40  # the object's brown, not the table's grey over it
    tx, ty = np.rint(r.to_pixel(0, obj + [0.15, 0.25, 0.0])).astype(int)  # table only, away from everything
    assert img[ty, tx].min() > 170  # faint
    sx, sy = np.rint(r.to_pixel(1, np.array([1.1, 0.75, 0.41]))).astype(int)  # the table's edge in the side view
    assert img[sy, sx].max() < 130  # solid
    env.close()
