"""The cube's position from gym-hil's front camera (common/tasks/panda/camera.py, colours.py): real frames of
``panda:pick``'s scenes rendered with MuJoCo's renderer, the estimate against the cube's true position; the
not-found result for frames without the cube; the back-projection against this test's own pinhole formula.

Tolerance: ``khgrl.benchmarks.camera_scene`` over 200 scenes (docs/camera_scene.json) gave a p95 error of 4.7 mm
(max 6.4 mm) in (x, y) with the occlusion model; the tests allow 2 x p95, rounded up: 10 mm."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gym_hil", reason="gym-hil is a project dependency: pip install -e .")

from khgrl.common.tasks.panda.arm import REGION, PandaPosition  # noqa: E402
from khgrl.common.tasks.panda.camera import (  # noqa: E402
    Camera,
    CubeNotFound,
    back_project,
    camera_of,
    describe_from_camera,
    front_renderer,
    locate_cube,
    render_front,
    silhouette,
)
from khgrl.common.tasks.panda.colours import gym_hil_colours, matches, scene_colours  # noqa: E402
from khgrl.common.tasks.panda.task import describe  # noqa: E402

TOL = 0.010  # metres: 2 x the benchmark's p95 (4.7 mm), rounded up


@pytest.fixture(scope="module")
def scene():
    env = PandaPosition(region=REGION)
    renderer = front_renderer(env.base.model, 128)
    yield env, renderer, scene_colours(env.base.model)
    renderer.close()
    env.close()


def _frame(env, renderer):
    return render_front(renderer, env.base.model, env.base.data)


def test_colours_come_from_the_model(scene) -> None:
    env, _, colours = scene
    assert colours.cube.hue == pytest.approx(300.0)  # rgba 0.6 0.3 0.6: r = b > g, (r - g) / (r - g) -> 300 degrees
    assert colours.cube.min_sat == pytest.approx(0.25)  # half of (0.6 - 0.3) / 0.6
    assert colours.table.hue == pytest.approx(210.0, abs=1.0)  # the checker's (0.1, 0.2, 0.3) and (0.2, 0.3, 0.4)
    assert 30.0 < colours.cube.hue_tol < 50.0 and colours.table.hue_tol < 6.0  # half the gaps to blue, light blue


@pytest.mark.parametrize("seed", [1, 4, 12])
def test_estimate_within_tolerance_of_the_truth(scene, seed: int) -> None:
    env, renderer, colours = scene
    obs, _ = env.reset(seed=seed)
    frame, cam = _frame(env, renderer)
    est = locate_cube(frame, cam, colours)
    truth = env.cube_pos
    assert np.linalg.norm(est[:2] - truth[:2]) < TOL, (est, truth)
    assert est[2] == pytest.approx(0.02)
    got = describe_from_camera(frame, cam)  # the colours from gym-hil's own scene file
    assert gym_hil_colours() == colours and set(got) == set(describe(obs))
    assert np.hypot(got["cube_x"] - truth[0], got["cube_y"] - truth[1]) < TOL


def test_occlusion_model_finds_a_cube_the_gripper_half_hides(scene) -> None:
    env, renderer, colours = scene
    env.reset(seed=11)  # the fingers hide more than half the cube (benchmark: 18 of 43 pixels seen)
    frame, cam = _frame(env, renderer)
    cube = matches(frame, colours.cube)
    assert cube.sum() < 0.6 * silhouette(env.cube_pos, cam, cube.shape).sum()
    with pytest.raises(CubeNotFound, match="where a cube would show"):  # the bare centroid's check rejects it
        locate_cube(frame, cam, colours, occlusion=False)
    assert np.linalg.norm(locate_cube(frame, cam, colours)[:2] - env.cube_pos[:2]) < TOL


def test_silhouette_matches_the_rendered_cube(scene) -> None:
    env, renderer, colours = scene
    env.reset(seed=12)  # the cube in full view
    frame, cam = _frame(env, renderer)
    cube = matches(frame, colours.cube)
    predicted = silhouette(env.cube_pos, cam, cube.shape) >= 0.5
    iou = (cube & predicted).sum() / (cube | predicted).sum()
    assert iou > 0.8, iou


def test_no_cube_in_the_frame_is_not_found(scene) -> None:
    env, renderer, colours = scene
    env.reset(seed=0)
    frame, cam = _frame(env, renderer)
    with pytest.raises(CubeNotFound):
        locate_cube(np.zeros_like(frame), cam, colours)  # blank
    with pytest.raises(CubeNotFound):
        locate_cube(np.full_like(frame, 255), cam, colours)  # white
    data = env.base.data
    data.jnt("block").qpos[:3] = (0.4, 2.5, 0.02)  # far to the side, out of the camera's view
    import mujoco

    mujoco.mj_forward(env.base.model, data)
    frame, cam = _frame(env, renderer)
    with pytest.raises(CubeNotFound):
        locate_cube(frame, cam, colours)
    env.reset(seed=12)
    frame, cam = _frame(env, renderer)
    _, cols = np.nonzero(matches(frame, colours.cube))
    cut = np.roll(frame, -(cols.min() + 2), axis=1)  # the image shifted: the cube's left part off its left edge
    with pytest.raises(CubeNotFound, match="border"):
        locate_cube(cut, cam, colours)


def _pinhole(point: np.ndarray, pos: np.ndarray, rot: np.ndarray, fovy: float, h: int, w: int) -> np.ndarray:
    """This test's own projection: camera frame x right, y up, looking along -z; row 0 at the top."""
    x, y, z = rot.T @ (point - pos)
    f = (h / 2) / np.tan(np.radians(fovy) / 2)
    return np.array([w / 2 + f * x / -z, h / 2 - f * y / -z])


def test_back_projection_inverts_the_pinhole(scene) -> None:
    env, _, _ = scene
    env.reset(seed=0)
    front = camera_of(env.base.model, env.base.data)
    assert np.allclose(front.pos, [1.3, 0.0, 0.7]) and front.fovy == pytest.approx(45.0)
    look = np.array([0.4, 0.0, 0.02]) - [0.2, -0.6, 1.1]  # a second camera: above and beside the table, rolled
    z = -look / np.linalg.norm(look)
    x = np.cross(look, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    roll = np.array([[np.cos(0.3), -np.sin(0.3), 0], [np.sin(0.3), np.cos(0.3), 0], [0, 0, 1]])
    other = Camera(pos=np.array([0.2, -0.6, 1.1]), rot=np.stack([x, np.cross(z, x), z], 1) @ roll, fovy=60.0)
    rng = np.random.default_rng(0)
    for cam, (h, w) in ((front, (128, 128)), (other, (120, 200))):
        for _ in range(5):
            point = np.array([rng.uniform(0.3, 0.5), rng.uniform(-0.15, 0.15), rng.uniform(0.0, 0.05)])
            uv = _pinhole(point, cam.pos, cam.rot, cam.fovy, h, w)
            assert 0 <= uv[0] <= w and 0 <= uv[1] <= h  # in view
            assert np.allclose(back_project(uv, cam, (h, w), z=point[2]), point, atol=1e-9)
