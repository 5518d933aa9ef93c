"""``panda:pick-camera``: panda:pick whose scene is what gym-hil's front camera sees (issue 37, point 5)."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MUJOCO_GL", "egl")

from khgrl.common.tasks.api import load_task  # noqa: E402
from khgrl.common.tasks.panda.arm import CUBE  # noqa: E402


@pytest.fixture(scope="module")
def envs():
    pick, seen = (load_task(spec).make_env(0) for spec in ("panda:pick", "panda:pick-camera"))
    yield pick, seen
    pick.close()
    seen.close()


@pytest.mark.parametrize("seed", [1, 11])
def test_the_first_observation_holds_the_cube_the_camera_sees(envs, seed: int) -> None:
    pick, seen = envs
    truth, _ = pick.reset(seed=seed)
    first, info = seen.reset(seed=seed)
    assert info["cube_seen"] is True
    error = np.linalg.norm(first[CUBE][:2] - truth[CUBE][:2])
    assert 0.0 < error <= 0.007 and error == pytest.approx(seen.last_error_m)  # estimated, within 7 mm
    mask = np.ones(truth.shape, bool)
    mask[CUBE.start:CUBE.start + 2] = False
    assert np.array_equal(first[mask], truth[mask])  # nothing else differs
    task = load_task("panda:pick-camera")
    assert task.scene.describe(first) == {"cube_x": first[CUBE][0], "cube_y": first[CUBE][1]}
    action = np.array([0.45, 0.05, 0.2])
    for _ in range(3):  # after the reset: panda:pick's observations
        a, *_ = pick.step(action)
        b, *_ = seen.step(action)
        assert np.array_equal(a, b)


def test_a_cube_not_seen_is_reached_for_at_the_regions_centre(envs) -> None:
    """Scene seed 3: the gripper hides too much of the cube for locate_cube (CubeNotFound)."""
    _, seen = envs
    before = seen.not_seen
    first, info = seen.reset(seed=3)
    (x0, y0), (x1, y1) = seen.region
    assert info["cube_seen"] is False and seen.not_seen == before + 1
    assert np.allclose(first[CUBE][:2], [(x0 + x1) / 2, (y0 + y1) / 2])


def test_pixels_camera_locates_the_cube_in_its_own_front_frame(envs) -> None:
    """``panda:pick-pixels-camera``: ``panda:pick-pixels`` whose first ``environment_state`` holds the estimate that
    ``panda:pick-camera`` makes from the same frame; its frames, state and later observations are pick-pixels'."""
    _, seen = envs
    pixels, located = (load_task(spec).make_env(0) for spec in ("panda:pick-pixels", "panda:pick-pixels-camera"))
    try:
        for seed in (1, 3):  # seed 3: the cube is not found (the region's centre)
            truth, _ = pixels.reset(seed=seed)
            first, info = located.reset(seed=seed)
            flat, seen_info = seen.reset(seed=seed)
            assert info["cube_seen"] is seen_info["cube_seen"] is (seed == 1)
            np.testing.assert_array_equal(first["environment_state"][:2], flat[CUBE][:2])
            assert not np.array_equal(first["environment_state"][:2], truth["environment_state"][:2])
            for key in ("front", "wrist", "agent_pos"):
                np.testing.assert_array_equal(first[key], truth[key])
            a, *_ = pixels.step(np.array([0.45, 0.05, 0.2]))
            b, *_ = located.step(np.array([0.45, 0.05, 0.2]))
            np.testing.assert_array_equal(a["environment_state"], b["environment_state"])
        assert located.sight.seen == 1 and located.sight.not_seen == 1
        assert load_task("panda:pick-pixels-camera").image_keys == ("front", "wrist")
    finally:
        pixels.close()
        located.close()
