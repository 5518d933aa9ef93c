"""The passage world drawn by the one renderer, :class:`khgrl.common.tasks.render.TaskRenderer` (headless): what the
README's figures show (walls with open gaps, obstacle, start, goal, demonstrations, KMP mean, band, robot, P_t, P_h,
legend, text strip), ``PassageEnv.render`` and the figure command."""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from khgrl.common.tasks import figure  # noqa: E402
from khgrl.common.tasks.passage.env import PassageEnv  # noqa: E402
from khgrl.common.tasks.passage.scenarios import get_scenario  # noqa: E402
from khgrl.common.tasks.render import TaskFrame, TaskRenderer, frame_from_env  # noqa: E402
from khgrl.common.tasks.render_parts import band_layer  # noqa: E402

W, H, STRIP = 600, 660, 60


@pytest.fixture(scope="module", params=["high_cov", "low_cov"])
def scene(request):
    env = PassageEnv(request.param)
    return env, TaskRenderer(env.descriptor(f"passage:{request.param}"), (W, H), strip_height=STRIP, legend=True)


def _frame(**kw) -> TaskFrame:
    """Robot and desired position parked in the empty lower-right corner unless given."""
    kw.setdefault("position", np.array([0.85, 0.12]))
    kw.setdefault("desired", np.array([0.75, 0.12]))
    return TaskFrame(**kw)


def _px(img: np.ndarray, r: TaskRenderer, p) -> np.ndarray:
    x, y = np.rint(r.to_pixel(0, np.asarray(p, dtype=float))).astype(int)
    return img[y, x].astype(int)


def _dark(c) -> bool:
    return max(c) < 130


def _brown(c) -> bool:
    r, g, b = c
    return r > g + 30 and g > b + 10 and 90 < r < 220


def _red(c) -> bool:
    r, g, b = c
    return r > 150 and g < 110 and b < 110


def test_walls_dark_with_open_gaps(scene) -> None:
    env, r = scene
    img = r.render_rgb(_frame())
    for wall in env.scenario.walls:
        for y in (0.05, 0.3, wall.gap_lo - 0.03, wall.gap_hi + 0.03, 0.95):
            assert _dark(_px(img, r, (wall.x, y))), (wall, y)
        ys = np.linspace(wall.gap_lo + 0.005, wall.gap_hi - 0.005, 9)
        assert not any(_dark(_px(img, r, (wall.x, y))) for y in ys)  # the passage is open


def test_obstacle_brown_only_in_high_cov(scene) -> None:
    env, r = scene
    img = r.render_rgb(_frame(), show_mean=False, show_demos=False)
    obs = get_scenario("high_cov").obstacle
    c = np.asarray(obs.center)
    rng = np.random.default_rng(1)
    ang, rad = rng.uniform(0, 2 * np.pi, 200), obs.radius * 0.8 * np.sqrt(rng.uniform(0, 1, 200))
    brown = np.mean([_brown(_px(img, r, c + [a * np.cos(t), a * np.sin(t)])) for a, t in zip(rad, ang)])
    if env.scenario.obstacle is not None:
        assert brown > 0.6
    else:
        assert brown < 0.05


def test_start_and_goal_marked(scene) -> None:
    env, r = scene
    img = r.render_rgb(_frame(), show_mean=False, show_demos=False)
    x, y = np.rint(r.to_pixel(0, np.asarray(env.scenario.goal))).astype(int)
    ring = img[y - 8:y + 9, x - 8:x + 9].reshape(-1, 3).astype(int)
    assert np.sum((ring[:, 1] > ring[:, 0] + 50) & (ring[:, 1] > ring[:, 2] + 50)) > 10  # green
    x, y = np.rint(r.to_pixel(0, np.asarray(env.scenario.start))).astype(int)
    ring = img[y - 8:y + 9, x - 8:x + 9].reshape(-1, 3).astype(int)
    assert np.sum((ring[:, 0] > ring[:, 1] + 50) & (ring[:, 2] > ring[:, 1] + 50)) > 10  # purple


def test_mean_red_and_demos_toggle(scene) -> None:
    env, r = scene
    mean = env.mapping.model.grid_mean
    idx = np.linspace(20, len(mean) - 20, 60).astype(int)
    img = r.render_rgb(_frame())
    assert np.mean([_red(_px(img, r, mean[i])) for i in idx]) > 0.7
    assert np.mean([_red(_px(r.render_rgb(_frame(), show_mean=False), r, mean[i])) for i in idx]) < 0.2
    demo = env.world.demos[int(np.argmax(env.world.demos[:, 200, 1]))][150:250]  # the outermost one
    with_demos = r.render_rgb(_frame(), show_mean=False)
    without = r.render_rgb(_frame(), show_mean=False, show_demos=False)
    assert np.mean([np.any(_px(with_demos, r, p) != _px(without, r, p)) for p in demo]) > 0.7


def test_band_tints_and_degenerate_bands(scene) -> None:
    env, r = scene
    mean = env.mapping.model.grid_mean
    band = np.stack([mean - 0.25, mean + 0.25], axis=1)
    p = (0.525, 0.715)  # inside that band, off the demonstrations and grid lines
    plain = _px(r.render_rgb(_frame(), show_demos=False), r, p)
    tinted = _px(r.render_rgb(_frame(band=band), show_demos=False), r, p)
    assert min(plain) > 235 and tinted[2] > tinted[0] + 30
    for b in (np.stack([mean - 1e4, mean + 1e4], axis=1), np.zeros((0, 2, 2))):
        assert r.render_rgb(_frame(band=b)).shape == (H, W, 3)
    thin = np.stack([mean, mean], axis=1)
    thin[5] = np.nan  # non-finite rows are skipped
    r.render_rgb(_frame(band=thin))
    with pytest.raises(ValueError):
        band_layer(np.zeros((10, 2)), 100, lambda q: q)


def test_legend_in_view_corner(scene) -> None:
    env, r = scene
    plain = TaskRenderer(r.descriptor, (W, H), strip_height=STRIP).render_rgb(_frame())
    img = r.render_rgb(_frame())
    rect = r.views[0].rect
    corner = np.any(img != plain, axis=2)
    assert corner[rect.top:rect.top + 100, rect.left:rect.left + 150].sum() > 2000
    assert not corner[rect.bottom - 100:rect.bottom, rect.right - 150:rect.right].any()


def test_trail_correction_and_strip(scene) -> None:
    env, r = scene
    env.reset()
    for _ in range(60):
        env.set_correction(np.array([0.3, 0.8]) if env.t >= 50 else None)
        env.step(np.zeros(2))
    f = frame_from_env(env)
    env.set_correction(None)
    img = r.render_rgb(f)
    assert f.human_active and max(_px(img, r, f.correction)) < 60  # the black cross of P_h
    assert tuple(img[r.views[0].rect.top + 1, r.views[0].rect.centerx]) == (255, 140, 0)  # orange frame
    strip = img[H - STRIP + 8:].astype(int)
    assert (strip.sum(axis=2) < 200).sum() > 100  # the status text
    blank = r.render_rgb(_frame())[H - STRIP + 8:]
    assert len(np.unique(blank.reshape(-1, 3), axis=0)) == 1  # plain grey without text


def test_env_render_is_the_task_renderer_and_needs_no_display() -> None:
    if pygame.display.get_init():
        pygame.display.quit()
    env = PassageEnv("low_cov", render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.zeros(2))
    img = env.render()
    ref = TaskRenderer(env.descriptor()).render_rgb(frame_from_env(env))
    np.testing.assert_array_equal(img, ref)
    assert not pygame.display.get_init()
    with pytest.raises(ValueError, match="render_mode"):
        PassageEnv("low_cov", render_mode="human")  # one renderer: the GUI is the window


def test_figure_command_writes_the_documented_png(tmp_path) -> None:
    out = tmp_path / "fig.png"
    assert figure.main(["passage:low_cov", "--steps", "235", "--out", str(out)]) == 0
    img = pygame.surfarray.array3d(pygame.image.load(str(out))).swapaxes(0, 1)
    np.testing.assert_array_equal(img, figure.task_figure("passage:low_cov", 235))
    assert img.shape == (660, 600, 3)
    assert tuple(img[11, 300]) == (255, 140, 0)  # the scripted human corrects at step 235: orange frame
