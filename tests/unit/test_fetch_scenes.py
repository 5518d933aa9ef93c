"""Fetch scenes that change every episode (common/tasks/fetch/scenes.py, scene_env.py; issue 22): ``fetch:random``
places the object at random from the reset's seed, in its stated region; ``describe`` and ``via_points`` read it
from the first observation; the scripted humans act only where intended; ``fetch:obstacle``'s block is a real MuJoCo
body on the carry path that a mean adapted only at the grasp runs into (the task fails without the human), while the
human's lift over it succeeds.

The adapted mean is computed here independently by the rule of the task API (a via-point replaces the reference
point at its grid step, Sigma = I / precision; common/kmp/adapt.py), refitting the LC-NS-KMP directly
(benchmarks/fetch_scenes.py)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gymnasium_robotics", reason="gymnasium-robotics is a project dependency: pip install -e .")

from khgrl.benchmarks.fetch_scenes import adapted_mean  # noqa: E402
from khgrl.benchmarks.fetch_scenes import rollout as _rollout  # noqa: E402
from khgrl.common.tasks.api import load_task, scene_seed  # noqa: E402
from khgrl.common.tasks.fetch.scene_env import (  # noqa: E402
    MIN_START_DISTANCE,
    OBJECT_REGION,
    OBSTACLE_HALF,
    OBSTACLE_TOP,
    box_gap,
)
from khgrl.common.tasks.fetch.scenes import AFTER_GRASP, CLEAR, NEAR, VIA_PHASES, grasp_path  # noqa: E402
from khgrl.common.tasks.fetch.teacher import DEMO_OBJECT, GOAL, START  # noqa: E402
from khgrl.common.tasks.kgrl_env import KGRLEnv  # noqa: E402
from khgrl.common.tasks.world import build_task_world  # noqa: E402

SCENES = [scene_seed(3, k) for k in range(1, 9)]


def rollout(env, obs, path, human=None) -> tuple[bool, int]:
    """(success at the end, steps touching the obstacle) of commanding ``path`` (the human's P_h where given)."""
    return _rollout(env, obs, path, human)[:2]


@pytest.fixture(scope="module")
def random_task():
    return load_task("fetch:random")


@pytest.fixture(scope="module")
def obstacle_task():
    return load_task("fetch:obstacle")


@pytest.fixture(scope="module")
def random_env(random_task):
    env = random_task.make_env(0)
    yield env
    env.close()


@pytest.fixture(scope="module")
def obstacle_env(obstacle_task):
    env = obstacle_task.make_env(0)
    yield env
    env.close()


def test_placements_follow_the_seed_inside_the_region(random_task, random_env) -> None:
    (x0, y0), (x1, y1) = OBJECT_REGION
    seen = []
    for s in SCENES:
        obs, _ = random_env.reset(seed=s)
        xy = obs[3:5].copy()
        assert x0 <= xy[0] <= x1 and y0 <= xy[1] <= y1, xy
        assert np.linalg.norm(xy - START[:2]) >= MIN_START_DISTANCE
        assert obs[5] == pytest.approx(DEMO_OBJECT[2], abs=2e-3)  # on the table
        np.testing.assert_allclose(obs[25:28], GOAL)  # the goal is fixed
        assert random_task.scene.describe(obs) == {"object_x": float(xy[0]), "object_y": float(xy[1])}
        seen.append(xy)
    seen = np.array(seen)
    assert min(np.linalg.norm(a - b) for i, a in enumerate(seen) for b in seen[i + 1:]) > 1e-3  # all different
    assert np.ptp(seen[:, 0]) > 0.08 and np.ptp(seen[:, 1]) > 0.12  # spread over the region, not a band
    obs, _ = random_env.reset(seed=SCENES[2])
    np.testing.assert_array_equal(obs[3:5], seen[2])  # the same seed, the same scene
    obs2, _ = random_env.reset()  # no seed: the environment's generator goes on to another scene
    assert np.linalg.norm(obs2[3:5] - seen[2]) > 1e-3


def test_via_points_pin_the_grasp_at_the_observed_object(random_task, random_env) -> None:
    n = random_task.demos.shape[1]
    for s in SCENES[:3]:
        obs, _ = random_env.reset(seed=s)
        obj = obs[3:6]
        vias = list(random_task.scene.via_points(obs))
        steps = [int(round(v.phase * (n - 1))) for v in vias]
        assert len(vias) == 16 and steps == list(range(steps[0], steps[0] + 16))  # every grid step of the grasp
        assert VIA_PHASES[0] - 0.01 <= vias[0].phase and vias[-1].phase <= VIA_PHASES[1]
        np.testing.assert_allclose(vias[0].position, obj + [0, 0, 0.10], atol=1e-3)  # above the object at 0.24
        held = [v for v in vias if v.phase >= 0.325]  # the teacher's keyframes 0.32-0.42: at the object
        assert len(held) >= 7 and all(np.allclose(v.position, obj, atol=1e-9) for v in held)
        np.testing.assert_allclose([v.position for v in vias], grasp_path(obj, n)[steps])
        mean = adapted_mean(build_task_world(random_task), vias)
        err = max(float(np.linalg.norm(mean[t] - v.position)) for t, v in zip(steps, vias))
        assert err < 2e-3, err  # the adapted mean passes within 2 mm of every via-point


def test_tasks_build_and_the_obstacle_is_observed(random_task, obstacle_task, obstacle_env) -> None:
    for task in (random_task, obstacle_task):
        world = build_task_world(task)
        assert world.demos.shape == (6, 100, 3) and task.scene is not None and task.scene.region
    env = KGRLEnv(obstacle_task, seed=0)
    assert env.observation_space.shape == (31 + 1 + 3,)
    obs, _ = env.reset(seed=SCENES[0])
    env.close()
    inner, _ = obstacle_env.reset(seed=SCENES[0])
    assert obstacle_env.observation_space.contains(inner) and inner.shape == (31,)
    np.testing.assert_allclose(obs[28:31], inner[28:31], atol=1e-6)
    assert inner[30] == pytest.approx(OBSTACLE_TOP - OBSTACLE_HALF[2])
    place = obstacle_task.scene.describe(inner)
    assert set(place) == {"object_x", "object_y", "obstacle_x", "obstacle_y"} and place["obstacle_x"] == inner[28]


def test_the_scripted_humans_act_only_where_intended(random_task, obstacle_task, random_env) -> None:
    obs, _ = random_env.reset(seed=SCENES[0])
    obj = obs[3:6].copy()
    grasp, obstacle = random_task.scripted_human, obstacle_task.scripted_human
    mean = DEMO_OBJECT + [0, 0, 0.05]
    off = obj + [0.05, 0, 0]
    assert grasp(mean, phase=0.33, position=off, obs=None) is None  # no observation yet
    assert grasp(mean, phase=0.10, position=off, obs=obs) is None  # not at the grasp
    assert grasp(mean, phase=0.60, position=off, obs=obs) is None
    assert grasp(mean, phase=0.33, position=obj + [0.004, 0, 0.05], obs=obs) is None  # the gripper is at the object
    np.testing.assert_allclose(grasp(mean, phase=0.33, position=off, obs=obs), [obj[0], obj[1], mean[2]])
    scene = np.concatenate([obs, [1.35, 0.86, OBSTACLE_TOP - OBSTACLE_HALF[2]]])
    centre = scene[28:31]
    before = np.array([1.35, 0.86 - OBSTACLE_HALF[1] - NEAR + 0.01, 0.60])  # on the way, within NEAR
    far = np.array([1.35, 0.86 - OBSTACLE_HALF[1] - NEAR - 0.02, 0.60])
    after = np.array([1.35, 0.86 + OBSTACLE_HALF[1] + 0.04, 0.60])  # past it, toward the goal
    assert box_gap(before, centre) < NEAR < box_gap(far, centre)
    np.testing.assert_allclose(obstacle(before, phase=0.6, position=before, obs=scene),
                               [before[0], before[1], OBSTACLE_TOP + CLEAR])
    for m, ph in ((far, 0.6), (after, 0.8), (before, AFTER_GRASP - 0.01), (before + [0, 0, 0.2], 0.6)):
        assert obstacle(m, phase=ph, position=m, obs=scene) is None, (m, ph)
    np.testing.assert_allclose(obstacle(mean, phase=0.33, position=off, obs=scene), [obj[0], obj[1], mean[2]])


def test_the_obstacle_blocks_the_adapted_mean_and_the_human_lifts_over_it(obstacle_task, obstacle_env) -> None:
    """In every scene the carried object's path under the mean adapted at the grasp crosses the block (geometry) and
    touches it in MuJoCo, and the task fails in most; lifted over it by the scripted human, it succeeds in most."""
    n, crossed, plain, helped = obstacle_task.demos.shape[1], 0, [], []
    obstacle_world = build_task_world(obstacle_task)
    for s in SCENES[:6]:
        obs, _ = obstacle_env.reset(seed=s)
        mean = adapted_mean(obstacle_world, obstacle_task.scene.via_points(obs))
        carry = mean[int(0.45 * (n - 1)):int(0.88 * (n - 1))]
        centre = obs[28:31]
        # the held object (2.5 cm half, centred at the gripper) overlaps the block at some step of the carry
        crossed += any(box_gap(p, centre) < 0.025 and p[2] - 0.025 < OBSTACLE_TOP for p in carry)
        plain.append(rollout(obstacle_env, obs, mean))
        obs, _ = obstacle_env.reset(seed=s)
        helped.append(rollout(obstacle_env, obs, mean, obstacle_task.scripted_human))
    assert crossed == 6
    assert all(touching > 0 for _, touching in plain)  # a real body: the arm or the object runs into it
    assert sum(ok for ok, _ in plain) <= 1, plain
    assert sum(ok for ok, _ in helped) >= 5, helped
