"""The Fetch arm adapter (common/tasks/fetch/arm.py) on the real gymnasium-robotics MuJoCo environment: the gripper
tracks the commanded desired position when unobstructed, the gripper follows its phase schedule, the object and
goal are placed as asked, and the environment passes Gymnasium's checker behind the KGRL mapping."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

pytest.importorskip("gymnasium_robotics", reason="gymnasium-robotics is a project dependency: pip install -e .")

from khgrl.common.tasks.fetch.arm import MAX_STEP, FetchPosition, GripperSchedule, fetch_command  # noqa: E402


@pytest.fixture()
def env():
    e = FetchPosition(horizon=60)
    yield e
    e.close()


def test_command_is_the_clipped_displacement() -> None:
    np.testing.assert_allclose(fetch_command([1.0, 1.0, 1.0], [1.0, 1.0, 1.0]), 0.0)
    np.testing.assert_allclose(fetch_command([1.01, 0.9, 1.0], [1.0, 1.0, 1.0]), [0.01 / MAX_STEP, -1.0, 0.0])


def test_the_gripper_tracks_a_commanded_position(env) -> None:
    """A target 13 cm away: within 1.5 cm after 3 steps and 2 mm after 6 (Fetch's mocap moves <= 5 cm a step)."""
    env.reset(seed=0)
    target = env.gripper_pos + np.array([0.1, -0.05, -0.07])
    errors = []
    for _ in range(8):
        env.step(target)
        errors.append(float(np.linalg.norm(env.gripper_pos - target)))
    assert errors[2] < 0.015 and max(errors[5:]) < 0.002, errors


def test_the_gripper_follows_a_moving_command(env) -> None:
    """A path at 2 cm per step (slower than the 5 cm limit): the gripper stays within 2.5 cm of it throughout."""
    env.reset(seed=1)
    start = env.gripper_pos
    path = start + np.linspace(0, 1, 30)[:, None] * np.array([0.2, 0.3, -0.1])
    lag = []
    for p in path:
        env.step(p)
        lag.append(float(np.linalg.norm(env.gripper_pos - p)))
    assert max(lag) < 0.025 and lag[-1] < 0.025, lag


def test_gripper_schedule_and_placement() -> None:
    sched = GripperSchedule(close_at=0.4, open_at=0.8)
    assert [sched(s) for s in (0.0, 0.39, 0.4, 0.79, 0.8, 1.0)] == [1.0, 1.0, -1.0, -1.0, 1.0, 1.0]
    e = FetchPosition(horizon=20, object_xy=(1.25, 0.65), goal=(1.45, 0.9, 0.6))
    obs, _ = e.reset(seed=3)
    np.testing.assert_allclose(e.object_pos[:2], [1.25, 0.65], atol=1e-9)
    np.testing.assert_allclose(obs[-3:], [1.45, 0.9, 0.6])
    fingers = []
    for _ in range(20):
        obs, r, term, trunc, info = e.step(e.gripper_pos)
        fingers.append(float(obs[9] + obs[10]))  # finger joint positions: wide open, then closing
    assert trunc and not term and info["success"] is False
    assert fingers[-1] < fingers[5] - 0.01  # closed after the schedule's close_at (phase 0.35 by default)
    e.close()


def test_fetch_behind_the_kgrl_mapping_is_a_clean_gym_env() -> None:
    from gymnasium.utils.env_checker import check_env
    from khgrl.common.tasks.api import Task
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    e = FetchPosition(horizon=40)
    e.reset(seed=0)
    start = e.gripper_pos
    s = np.linspace(0, 1, 40)[:, None]
    demos = np.stack([start + s * np.array([0.1, 0.05 * k, -0.05]) for k in (-1, 0, 1)])
    task = Task(name="fetch-reach", make_env=lambda seed: FetchPosition(horizon=40), demos=demos,
                workspace=((1.05, 0.4, 0.42), (1.55, 1.1, 0.9)), position=lambda obs: obs[:3])
    env = KGRLEnv(task)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    assert not [w for w in caught if "gymnasium" in str(w.filename)], [str(w.message) for w in caught]
    assert env.observation_space.shape == (28 + 1 + 3,) and env.action_space.shape == (3,)
    e.close()
    env.close()


def test_camera_frame_renders_the_arm_offscreen():
    """MuJoCo's own view of the arm (khgrl eval --gif puts it beside the task's views), offscreen through EGL."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = ("import numpy as np; from khgrl.common.tasks.fetch.task import make_task; "
            "env = make_task('moved').make_env(0); "
            "env.reset(seed=0); a = env.camera_frame(96); env.step(np.array([1.2, 0.75, 0.6])); "
            "b = env.camera_frame(96); "
            "print(a.shape, a.dtype, int(a.std() > 10), int(np.abs(a.astype(int) - b).sum() > 0))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "MUJOCO_GL": "egl"}, cwd=Path(__file__).resolve().parents[2])
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[-2] == "(96, 96, 3) uint8 1 1"  # an image with content, and the arm moved in it
