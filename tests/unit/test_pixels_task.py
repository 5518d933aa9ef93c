"""Tasks with camera observations (common/tasks/obs_spaces.py, kgrl_env.py) and ``panda:pick-pixels``
(common/tasks/panda/pixels.py): the policy's Dict space (keys, dtypes, shapes) and observations in it, gymnasium's
``check_env`` clean on ``panda:pick-pixels``' KGRLEnv, the robot's position read from the state vector, bad camera
declarations refused with a TaskError naming the key, and a vector task's observation space as before.

The camera variant of the passage world (``CameraRobot`` of deploy/examples/camera_task.py, a real environment
drawing the robot as a dot in a small image) checks the general path without MuJoCo; one ``panda:pick-pixels``
environment serves the Panda tests (building its world and gym-hil's model takes ~10 s)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env
from khgrl.common.tasks.api import TaskError, load_task
from khgrl.common.tasks.kgrl_env import KGRLEnv, make_inner_env
from khgrl.common.tasks.obs_spaces import MAX_CAMERAS, MAX_SIDE
from khgrl.common.tasks.spaces import observation_space as passage_space
from khgrl.deploy.examples.camera_task import SIDE, make_task


def camera_passage(images: dict | None = None, state_key: str | None = "pos", image_keys=("cam",)):
    """``passage:high_cov`` observing :class:`CameraRobot` (deploy/examples/camera_task.py)."""
    return make_task(images, state_key, image_keys)


@pytest.fixture(scope="module")
def panda():
    pytest.importorskip("gym_hil", reason="gym-hil is a project dependency: pip install -e .")
    env = KGRLEnv(load_task("panda:pick-pixels"), seed=0)
    yield env
    env.close()


def test_panda_pixels_spaces_and_observation(panda: KGRLEnv) -> None:
    space = panda.observation_space
    assert isinstance(space, spaces.Dict) and set(space.spaces) == {"state", "front", "wrist"}
    assert space["state"].dtype == np.float32 and space["state"].shape == (18 + 1 + 3,)  # agent_pos, s, deviation
    for key in ("front", "wrist"):
        assert space[key].dtype == np.uint8 and space[key].shape == (128, 128, 3)
    obs, _ = panda.reset(seed=5)
    assert space.contains(obs) and obs["state"].dtype == np.float32
    assert obs["state"][18] == 0.0  # the phase at reset
    assert "environment_state" not in obs  # the cube's true position is the task's, not the policy's
    front = obs["front"].astype(np.int32)
    assert front.std() > 10 and obs["wrist"].astype(np.int32).std() > 10  # rendered scenes, not blank frames
    other, _ = panda.reset(seed=6)  # another cube place: another front image
    assert np.abs(other["front"].astype(np.int32) - front).sum() > 0
    assert panda.descriptor("panda:pick-pixels").obs_dim == 22  # the wire's descriptor states the state part


def test_check_env_clean_on_panda_pixels(panda: KGRLEnv) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(panda, skip_render_check=True)
    assert [str(w.message) for w in caught] == []


def test_position_is_read_from_the_state(panda: KGRLEnv) -> None:
    obs, _ = panda.reset(seed=2)
    tcp = panda.inner.gripper_pos
    assert np.allclose(panda.position, panda.inner_obs["agent_pos"][15:18]) and np.allclose(panda.position, tcp)
    assert np.allclose(obs["state"][15:18], tcp, atol=1e-6)
    for _ in range(2):
        obs, *_ = panda.step(np.ones(3, np.float32))
    assert np.allclose(panda.position, panda.inner.gripper_pos)
    assert np.linalg.norm(panda.position - tcp) > 1e-3  # it moved, and the position followed the state
    assert np.allclose(panda.inner_obs["environment_state"], panda.inner.cube_pos)
    assert set(panda.placement) == {"cube_x", "cube_y"} and np.isclose(panda.placement["cube_x"],
                                                                       panda.inner.cube_pos[0])
    cube = panda.inner.cube_pos  # the scripted human reads the cube from the task-only key, as in panda:pick
    p_h = panda.task.scripted_human(cube + [0.05, 0.0, 0.1], phase=0.5, obs=panda.inner_obs)
    assert np.allclose(p_h, [cube[0], cube[1], cube[2] + 0.1])


def test_camera_passage_observes_state_and_image() -> None:
    env = KGRLEnv(camera_passage(), seed=0)
    assert set(env.observation_space.spaces) == {"state", "cam"}
    assert env.observation_space["state"].shape == (2 + 1 + 2,)
    obs, _ = env.reset(seed=0)
    assert np.allclose(obs["state"][:2], env.position) and obs["cam"].sum() == 3 * 255  # one white pixel
    for _ in range(3):
        obs, *_ = env.step(np.zeros(2, np.float32))
    assert env.observation_space.contains(obs) and np.allclose(obs["state"][:2], env.inner_obs["pos"])
    check_env(env, skip_render_check=True)


def _image(shape, dtype=np.uint8):
    return spaces.Box(0, 255, shape, dtype)


@pytest.mark.parametrize(("images", "state_key", "image_keys", "words"), [
    ({"cam": _image((SIDE, SIDE, 3), np.float32)}, "pos", ("cam",), ("'cam'", "uint8")),
    ({"cam": _image((SIDE, SIDE))}, "pos", ("cam",), ("'cam'", "3-D")),
    ({"cam": _image((MAX_SIDE + 1, SIDE, 3))}, "pos", ("cam",), ("'cam'", f"at most {MAX_SIDE}")),
    ({"cam": _image((SIDE, SIDE, 2))}, "pos", ("cam",), ("'cam'", "C in")),
    (None, "pos", ("cam", "nope"), ("'nope'", "not in")),
    (None, "nope", ("cam",), ("'nope'", "not in")),
    (None, "cam", ("cam",), ("'cam'", "state key")),
    (None, "pos", ("state",), ("'state'",)),
    (None, None, ("cam",), ("state_key=None",)),
    ({f"c{k}": _image((4, 4, 3)) for k in range(MAX_CAMERAS + 1)}, "pos",
     tuple(f"c{k}" for k in range(MAX_CAMERAS + 1)), (f"at most {MAX_CAMERAS} cameras",)),
])
def test_bad_camera_declaration_is_refused(images, state_key, image_keys, words) -> None:
    task = camera_passage(images, state_key, image_keys)
    with pytest.raises(TaskError) as err:
        make_inner_env(task, 0)
    assert all(w in str(err.value) for w in words), str(err.value)


def test_state_key_must_be_a_float_vector() -> None:
    task = camera_passage(state_key="cam", image_keys=("cam2",),
                          images={"cam": _image((SIDE, SIDE, 3)), "cam2": _image((SIDE, SIDE, 3))})
    with pytest.raises(TaskError, match="state key 'cam' must be a 1-D float Box"):
        make_inner_env(task, 0)


def test_vector_task_space_unchanged() -> None:
    env = KGRLEnv(load_task("passage:high_cov"), seed=0)
    assert env.cameras is None and env.observation_space == passage_space()  # the passage world's 5-D Box
    obs, _ = env.reset(seed=0)
    assert isinstance(obs, np.ndarray) and obs.dtype == np.float32 and obs.shape == (5,)
