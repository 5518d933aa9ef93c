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
