"""gym-hil's Panda pick-cube as a task (common/tasks/panda/): the adapter drives gym-hil's gripper to P_t, the reset
seed decides the cube's place (gym-hil's own placement ignores it), describe/via_points read the observation, the
scripted teacher's plan lifts the cube in the real MuJoCo environment wherever the cube is, the task builds, and the
scripted human acts only at the grasp.

One environment serves the whole module (gym-hil's constructor takes a few seconds: MuJoCo model and an EGL
renderer)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gym_hil", reason="gym-hil is a project dependency: pip install -e .")

from khgrl.common.tasks.api import load_task  # noqa: E402
from khgrl.common.tasks.panda.arm import CUBE, EE_STEP, REGION, TCP, PandaPosition  # noqa: E402
from khgrl.common.tasks.panda.task import (  # noqa: E402
    DEMO_CUBE,
    GRASP_Z,
    HORIZON,
    PHASES,
    VIA_PHASES,
    PandaGuide,
    demo_cubes,
    describe,
    teacher_plan,
    via_points,
)
from khgrl.common.tasks.world import build_task_world  # noqa: E402


@pytest.fixture(scope="module")
def task():
    return load_task("panda:pick")


@pytest.fixture(scope="module")
def env(task):
    e = task.make_env(0)
    yield e
    e.close()


def test_adapter_moves_the_gripper_to_p_t(env: PandaPosition) -> None:
    obs, _ = env.reset(seed=1)
    start = obs[TCP].copy()
    goal = start + np.array([-0.08, 0.05, 0.06])  # 11 cm away: 4 steps of 2.5 cm along x, then settling
    dist = [float(np.linalg.norm(goal - start))]
    for _ in range(10):
        obs, _, terminated, truncated, _ = env.step(goal)
        assert not (terminated or truncated)
        dist.append(float(np.linalg.norm(goal - obs[TCP])))
    assert dist[1] < dist[0] - 0.5 * EE_STEP and dist[3] < dist[1]  # it moves toward P_t from the first step
    assert dist[-1] < 0.01, dist  # and gets within 1 cm
    assert np.allclose(env.target, goal)  # gym-hil's controller target is P_t itself (no wind-up)
    assert env.observation_space.contains(obs) and obs[14] == 0.0  # gripper open (scaled command 0)


def test_reset_seed_decides_the_cube(env: PandaPosition) -> None:
    cubes = {}
    for seed in (3, 4, 5, 3):
        obs, _ = env.reset(seed=seed)
        cube = obs[CUBE]
        assert REGION[0][0] <= cube[0] <= REGION[1][0] and REGION[0][1] <= cube[1] <= REGION[1][1]
        assert abs(cube[2] - 0.02) < 1e-3  # on the table
        if seed in cubes:
            assert np.array_equal(cubes[seed], cube)  # the same seed, the same scene
        cubes[seed] = cube
    xy = [tuple(np.round(c[:2], 6)) for c in cubes.values()]
    assert len(set(xy)) == 3, xy  # different seeds, different places
    # gym-hil alone puts the cube at (0.5, 0) whatever the seed; this wrapper's own draw moved it
    assert all(np.hypot(c[0] - 0.5, c[1]) > 1e-3 for c in cubes.values())


def test_describe_and_via_points_read_the_observation(env: PandaPosition) -> None:
    obs, _ = env.reset(seed=7)
    cube = obs[CUBE]
    assert describe(obs) == {"cube_x": float(cube[0]), "cube_y": float(cube[1])}
    via = via_points(obs)
    steps = [round(v.phase * (HORIZON - 1)) for v in via]
    assert len(via) == 16 and steps == sorted(set(steps))  # 16 via-points on 16 different grid steps
    assert np.allclose([v.phase for v in via], np.round(VIA_PHASES * (HORIZON - 1)) / (HORIZON - 1))
    for v in via:  # from above the cube to the end of the lift: over the cube, never below the grasp height
        assert np.allclose(v.position[:2], cube[:2]) and v.position[2] >= GRASP_Z - 1e-12 and v.precision == 1e6
    t_grasp = round(PHASES["grasp"] * (HORIZON - 1))
    grasp = next(v for v in via if round(v.phase * (HORIZON - 1)) >= t_grasp)
    assert np.allclose(grasp.position, [cube[0], cube[1], GRASP_Z])
    moved = obs.copy()
    moved[CUBE] += [0.05, -0.04, 0.0]
    assert describe(moved)["cube_x"] == pytest.approx(float(cube[0]) + 0.05)
    for a, b in zip(via_points(moved), via):
        assert np.allclose(a.position, np.asarray(b.position) + [0.05, -0.04, 0.0])


def _rollout(env: PandaPosition, plan: np.ndarray) -> bool:
    """Step ``plan`` (desired positions) until gym-hil ends the episode; whether it succeeded."""
    for p in plan:
        _, _, terminated, truncated, info = env.step(p)
        if terminated or truncated:
            return bool(info["succeed"])
    return False


def test_teacher_lifts_the_cube_in_mujoco(task, env: PandaPosition) -> None:
    cubes = demo_cubes(len(task.demos))
    region = env.region
    try:
        for k in (0, len(task.demos) - 1):  # the task's own demonstrations, each with the cube where it was recorded
            env.region = (cubes[k][:2], cubes[k][:2])
            env.reset(seed=k)
            assert _rollout(env, task.demos[k]), k
        # a demonstration replayed where the cube is not (> 8 cm away): gym-hil's success is not reached
        far = cubes[0][:2] + np.where(cubes[0][:2] < DEMO_CUBE[:2], 0.08, -0.08) * [1.0, 1.5]
        env.region = (far, far)
        env.reset(seed=0)
        assert not _rollout(env, task.demos[0])
    finally:
        env.region = region
    # the teacher's plan for the cube it sees, in random scenes
    results = []
    for k in range(3):
        obs, _ = env.reset(seed=100 + k)
        results.append(_rollout(env, teacher_plan(obs[CUBE], rng=np.random.default_rng(k))))
    assert all(results), results


def test_task_world_builds(task) -> None:
    world = build_task_world(task)
    assert world.demos.shape == (6, HORIZON, 3) and world.out_dim == 3
    mean = np.asarray(world.model.grid_mean)
    hold = mean[round(PHASES["grasp"] * (HORIZON - 1)):round(PHASES["hold"] * (HORIZON - 1)) + 1]
    # the unadapted mean (GMR over the 6 demonstrations, then KMP) holds low near the demonstrations' average place
    assert GRASP_Z - 0.005 < hold[:, 2].min() < GRASP_Z + 0.01, hold
    assert np.all(np.abs(hold[:, :2] - demo_cubes(len(task.demos))[:, :2].mean(axis=0)) < 0.04), hold
    assert task.scene is not None and task.scene.via_points is not None and task.success_key == "succeed"
    assert np.allclose([v.position for v in task.scene.via_points(np.zeros(21))],
                       [v.position for v in via_points(np.zeros(21))])


def test_scripted_human_acts_only_at_the_grasp(env: PandaPosition) -> None:
    guide = PandaGuide()
    obs, _ = env.reset(seed=7)
    cube = obs[CUBE]
    off = np.array([DEMO_CUBE[0], DEMO_CUBE[1], 0.05])
    if np.hypot(*(cube[:2] - off[:2])) < 0.02:
        off[:2] += 0.05
    for phase in (0.0, 0.1, PHASES["above"] - 0.01, PHASES["lift"] + 0.01, 1.0):
        assert guide(off, phase=phase, obs=obs) is None  # approach and after the lift: hands off
    for phase in (PHASES["above"], PHASES["grasp"], PHASES["hold"], PHASES["lift"]):
        p_h = guide(off, phase=phase, obs=obs)
        assert p_h is not None and np.allclose(p_h, [cube[0], cube[1], off[2]])  # over the cube, same height
    on = np.array([cube[0] + 0.005, cube[1], 0.05])
    assert guide(on, phase=PHASES["grasp"], obs=obs) is None  # already at the cube: lets go
    assert guide(off, phase=PHASES["grasp"], obs=None) is None  # nothing seen yet


def test_camera_frame_renders_the_scene_offscreen(env: PandaPosition) -> None:
    obs, _ = env.reset(seed=2)
    a = env.camera_frame(96)
    env.step(obs[TCP] + [0.0, 0.0, 0.1])
    b = env.camera_frame(96)
    assert a.shape == b.shape == (96, 96, 3) and a.dtype == np.uint8
    assert a.std() > 5 and np.abs(a.astype(int) - b).mean() > 0.1  # a picture, and the arm moved in it
    assert env.camera_frame(200).shape == (200, 200, 3)  # larger than gym-hil's own 128 x 128 buffer
