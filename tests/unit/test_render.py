"""Headless tests of the pygame scene renderer (common/tasks/passage/render.py)."""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import time  # noqa: E402

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from khgrl.common.tasks.passage.render import FrameState, HumanWindow, SceneRenderer  # noqa: E402
from khgrl.common.tasks.passage.scenarios import get_scenario, make_demos  # noqa: E402

SIZE = 600
STRIP = 80


@pytest.fixture(scope="module")
def demos() -> np.ndarray:
    return make_demos("high_cov")


@pytest.fixture(scope="module")
def mean(demos: np.ndarray) -> np.ndarray:
    return demos.mean(axis=0)


@pytest.fixture(scope="module")
def renderer(demos: np.ndarray, mean: np.ndarray) -> SceneRenderer:
    return SceneRenderer(get_scenario("high_cov"), demos, mean, size=SIZE, strip_height=STRIP)


def _state(**kw) -> FrameState:
    """Robot and desired position parked in the empty lower-right corner unless given."""
    kw.setdefault("robot", np.array([0.85, 0.12]))
    kw.setdefault("desired", np.array([0.75, 0.12]))
    return FrameState(**kw)


def _px(img: np.ndarray, renderer: SceneRenderer, p) -> np.ndarray:
    x, y = renderer.world_to_pixel(np.asarray(p, dtype=float))
    return img[y, x].astype(int)


def _purple(c) -> bool:
    r, g, b = c
    return r > g + 50 and b > g + 50


def _green(c) -> bool:
    r, g, b = c
    return g > r + 50 and g > b + 50


def _brown(c) -> bool:
    r, g, b = c
    return r > g + 30 and g > b + 10 and 90 < r < 220


def _black(c) -> bool:
    return max(c) < 50


def _red(c) -> bool:
    r, g, b = c
    return r > 150 and g < 110 and b < 110


def _yellow(c) -> bool:
    r, g, b = c
    return r > 200 and g > 160 and b < 120


# ---------------------------------------------------------------------------- geometry


def test_render_rgb_shape_and_dtype(renderer: SceneRenderer) -> None:
    img = renderer.render_rgb(_state())
    assert img.shape == (SIZE + STRIP, SIZE, 3)
    assert img.dtype == np.uint8
    assert img.flags["C_CONTIGUOUS"]


def test_render_rgb_other_size(demos: np.ndarray, mean: np.ndarray) -> None:
    r = SceneRenderer(get_scenario("low_cov"), demos, mean, size=240, strip_height=30)
    img = r.render_rgb(_state(text=["hello"]))
    assert img.shape == (270, 240, 3)


def test_render_rgb_matches_draw_on_surface(renderer: SceneRenderer) -> None:
    st = _state(text=["a line"], phase=0.3)
    img = renderer.render_rgb(st)
    surf = pygame.Surface((SIZE, SIZE + STRIP))
    renderer.draw(surf, st)
    ref = np.frombuffer(pygame.image.tobytes(surf, "RGB"), dtype=np.uint8).reshape(SIZE + STRIP, SIZE, 3)
    np.testing.assert_array_equal(img, ref)


def test_world_pixel_round_trip(renderer: SceneRenderer) -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, size=(200, 2))
    px = renderer.world_to_pixel(p)
    assert px.dtype.kind == "i" and px.shape == (200, 2)
    back = renderer.pixel_to_world(px)
    assert back.dtype.kind == "f"
    np.testing.assert_allclose(back, p, atol=0.51 / (SIZE - 1))
    ints = rng.integers(0, SIZE, size=(200, 2))
    np.testing.assert_array_equal(renderer.world_to_pixel(renderer.pixel_to_world(ints)), ints)
    # corners, y up in the world and down in pixels
    np.testing.assert_array_equal(renderer.world_to_pixel(np.array([0.0, 0.0])), [0, SIZE - 1])
    np.testing.assert_array_equal(renderer.world_to_pixel(np.array([1.0, 1.0])), [SIZE - 1, 0])
    assert renderer.world_to_pixel(np.array([0.5, 0.9]))[1] < renderer.world_to_pixel(np.array([0.5, 0.1]))[1]


# ---------------------------------------------------------------------------- pixel colours


def test_robot_is_purple(renderer: SceneRenderer) -> None:
    robot = np.array([0.4, 0.3])
    img = renderer.render_rgb(_state(robot=robot))
    assert _purple(_px(img, renderer, robot))
    # with the desired-position ring on top of the robot the robot still shows through its hole
    img = renderer.render_rgb(_state(robot=robot, desired=robot))
    assert _purple(_px(img, renderer, robot))


def test_desired_ring_is_orange_and_hollow(renderer: SceneRenderer) -> None:
    desired = np.array([0.6, 0.25])
    img = renderer.render_rgb(_state(desired=desired))
    cx, cy = renderer.world_to_pixel(desired)
    # somewhere on a small circle around the point is orange; the centre is not
    ring = img[cy - 14 : cy + 15, cx - 14 : cx + 15].reshape(-1, 3).astype(int)
    orange = (ring[:, 0] > 220) & (ring[:, 1] > 80) & (ring[:, 1] < 170) & (ring[:, 2] < 80)
    assert orange.sum() > 20
    r, g, b = img[cy, cx].astype(int)
    assert not (r > 220 and 80 < g < 170 and b < 80)


def test_goal_is_green(renderer: SceneRenderer) -> None:
    sc = renderer.scenario
    img = renderer.render_rgb(_state())
    assert _green(_px(img, renderer, sc.goal))


def test_obstacle_is_brown(renderer: SceneRenderer) -> None:
    obs = renderer.scenario.obstacle
    assert obs is not None
    img = renderer.render_rgb(_state())
    # a pixel off the demonstrations and the mean
    c = np.array(obs.center)
    assert _brown(_px(img, renderer, c + np.array([0.0, -0.045])))
    # and most of the disc
    rng = np.random.default_rng(1)
    ang = rng.uniform(0, 2 * np.pi, 300)
    rad = obs.radius * 0.85 * np.sqrt(rng.uniform(0, 1, 300))
    pts = c + np.c_[rad * np.cos(ang), rad * np.sin(ang)]
    brown = [_brown(_px(img, renderer, p)) for p in pts]
    assert np.mean(brown) > 0.6
    # and nothing brown far outside it
    assert not _brown(_px(img, renderer, c + np.array([0.0, 0.3])))


def test_no_obstacle_in_low_cov(demos: np.ndarray, mean: np.ndarray) -> None:
    r = SceneRenderer(get_scenario("low_cov"), None, None)
    img = r.render_rgb(_state())
    assert not _brown(_px(img, r, (0.5, 0.5)))


@pytest.mark.parametrize("name", ["high_cov", "low_cov"])
def test_walls_black_gaps_open(name: str) -> None:
    sc = get_scenario(name)
    demos = make_demos(name)
    r = SceneRenderer(sc, demos, demos.mean(axis=0))
    img = r.render_rgb(_state())
    for wall in sc.walls:
        for y in (0.05, 0.3, wall.gap_lo - 0.03, wall.gap_hi + 0.03, 0.95):
            assert _black(_px(img, r, (wall.x, y))), (wall, y)
        assert not _black(_px(img, r, (wall.x, wall.gap_center)))
        # the gap is highlighted yellow (demo dashes may cross part of it)
        ys = np.linspace(wall.gap_lo + 0.003, wall.gap_hi - 0.003, 15)
        xs = wall.x + np.array([-0.008, 0.0, 0.008])
        cols = [_px(img, r, (x, y)) for x in xs for y in ys]
        assert not any(_black(c) for c in cols)
        assert np.mean([_yellow(c) for c in cols]) > 0.6
        # next to the wall, away from everything, is white background or grid
        assert min(_px(img, r, (wall.x + 0.04, 0.93))) > 200


def test_mean_is_red(renderer: SceneRenderer, mean: np.ndarray) -> None:
    img = renderer.render_rgb(_state())
    idx = np.linspace(20, len(mean) - 20, 60).astype(int)
    red = [_red(_px(img, renderer, mean[i])) for i in idx]
    assert np.mean(red) > 0.7
    # hiding it removes the red
    img2 = renderer.render_rgb(_state(), show_mean=False)
    red2 = [_red(_px(img2, renderer, mean[i])) for i in idx]
    assert np.mean(red2) < 0.2


def test_demos_drawn_dashed_blue(renderer: SceneRenderer, demos: np.ndarray) -> None:
    img = renderer.render_rgb(_state(), show_mean=False)
    d = demos[int(np.argmax(demos[:, 200, 1]))]  # the outermost demo, clear of the others mid-way
    pts = d[150:250]
    blue = [(lambda c: c[2] > c[0] + 60)(_px(img, renderer, p)) for p in pts]
    # dashed: clearly blue along part of it, clearly not along another part
    assert 0.2 < np.mean(blue) < 0.9
    img2 = renderer.render_rgb(_state(), show_mean=False, show_demos=False)
    blue2 = [(lambda c: c[2] > c[0] + 60)(_px(img2, renderer, p)) for p in pts]
    assert np.mean(blue2) < 0.05


def test_band_tints_region(renderer: SceneRenderer, mean: np.ndarray) -> None:
    band = np.stack([mean - 0.25, mean + 0.25], axis=1)
    p = (0.525, 0.715)  # inside the band, outside the demonstrations' fan, off grid lines
    plain = _px(renderer.render_rgb(_state()), renderer, p)
    tinted = _px(renderer.render_rgb(_state(band=band)), renderer, p)
    assert min(plain) > 235  # white background
    assert tinted[2] > tinted[0] + 30 and tinted[2] > 200  # light blue
    off = _px(renderer.render_rgb(_state(band=band), show_band=False), renderer, p)
    np.testing.assert_array_equal(off, plain)
    # well outside the band stays white
    assert min(_px(renderer.render_rgb(_state(band=band)), renderer, (0.525, 0.92))) > 235


def test_band_degenerate_inputs(renderer: SceneRenderer, mean: np.ndarray) -> None:
    huge = np.stack([mean - 1e4, mean + 1e4], axis=1)
    img = renderer.render_rgb(_state(band=huge))
    assert img.shape == (SIZE + STRIP, SIZE, 3)
    thin = np.stack([mean, mean], axis=1)  # zero width: still drawn along the mean
    thin[5] = np.nan  # non-finite rows are skipped
    renderer.render_rgb(_state(band=thin))
    renderer.render_rgb(_state(band=np.zeros((0, 2, 2))))
    with pytest.raises(ValueError):
        renderer.render_rgb(_state(band=np.zeros((10, 2))))


def test_trail_and_correction(renderer: SceneRenderer, mean: np.ndarray) -> None:
    trail = np.c_[np.linspace(0.1, 0.5, 50), np.full(50, 0.2)]
    corr = np.array([0.45, 0.85])
    img = renderer.render_rgb(_state(trail=trail, correction=corr, human_active=True, phase=0.5))
    c = _px(img, renderer, (0.3, 0.2))
    assert c[0] > c[1] + 30 and c[2] > c[1] + 30  # purple trail
    assert _black(_px(img, renderer, corr))  # centre of the cross
    # the line from the mean point at the phase to P_h
    origin = mean[int(round(0.5 * (len(mean) - 1)))]
    mid = 0.5 * (origin + corr)
    assert max(_px(img, renderer, mid)) < 120
    # human-active frame
    r, g, b = img[SIZE // 2, 1].astype(int)
    assert r > 200 and 100 < g < 180 and b < 60


def test_text_strip(renderer: SceneRenderer) -> None:
    blank = renderer.render_rgb(_state(phase=0.0))
    strip_blank = blank[SIZE + 8 :, :, :]
    assert len(np.unique(strip_blank.reshape(-1, 3), axis=0)) == 1  # plain grey without text
    img = renderer.render_rgb(_state(phase=0.0, text=["episode 3  step 120/400", "L = 20.0  return -1.23"]))
    strip = img[SIZE + 8 :, :, :].astype(int)
    assert strip.std() > 5.0
    assert (strip.sum(axis=2) < 200).sum() > 100  # dark text pixels
    # the grey strip itself
    assert np.all(np.abs(img[SIZE + STRIP - 2, SIZE - 3].astype(int) - 226) < 8)
    # text stays in the strip: the world part is unchanged
    np.testing.assert_array_equal(img[: SIZE - 1], blank[: SIZE - 1])


def test_renderer_does_not_use_display(renderer: SceneRenderer) -> None:
    if pygame.display.get_init():
        pygame.display.quit()
    renderer.render_rgb(_state(text=["x"]))
    assert not pygame.display.get_init()


def test_render_speed(renderer: SceneRenderer, mean: np.ndarray) -> None:
    band = np.stack([mean - 0.1, mean + 0.1], axis=1)
    st = _state(band=band, trail=mean[:200], text=["a", "b", "c"], phase=0.5)
    renderer.render_rgb(st)
    t0 = time.perf_counter()
    for i in range(20):
        st.robot = mean[i * 10]
        renderer.render_rgb(st)
    per_frame = (time.perf_counter() - t0) / 20
    assert per_frame < 0.05, per_frame  # a few ms in practice; generous for loaded CI machines


# ---------------------------------------------------------------------------- human window


def test_human_window_dummy_driver(renderer: SceneRenderer, mean: np.ndarray) -> None:
    win = HumanWindow(renderer, title="test window")
    try:
        assert pygame.display.get_init()
        assert win.screen.get_size() == (SIZE, SIZE + STRIP)
        win.show(_state(text=["first"]))
        win.show(_state(robot=mean[100], desired=mean[101], trail=mean[:100], text=["second"]), fps=120)
        assert not win.closed
        shown = np.frombuffer(pygame.image.tobytes(win.screen, "RGB"), dtype=np.uint8)
        assert shown.reshape(SIZE + STRIP, SIZE, 3).std() > 0
    finally:
        win.close()
    assert win.closed
    assert not pygame.display.get_init()
    win.close()  # idempotent
    win.show(_state())  # no-op after close


def test_human_window_quit_event_closes(renderer: SceneRenderer) -> None:
    with HumanWindow(renderer) as win:
        pygame.event.post(pygame.event.Event(pygame.QUIT))
        win.show(_state())
        assert win.closed
    assert not pygame.display.get_init()
