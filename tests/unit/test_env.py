"""The passage world as a Gymnasium environment (common/tasks/passage/env.py): API, rewards (eqs. 7-11), episode end,
wall physics and the human-intervention path (eq. 6)."""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import warnings  # noqa: E402

import gymnasium as gym  # noqa: E402
import khgrl.common.tasks.passage.env  # noqa: E402,F401  (registers khgrl/Passage-v0)
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402
from khgrl.common.kmp.mapping import KGRLMapping  # noqa: E402
from khgrl.common.kmp.scale import ScaleModel  # noqa: E402
from khgrl.common.tasks.passage.env import ENV_ID, PassageEnv, build_world  # noqa: E402

SCENARIOS = ("high_cov", "low_cov")


@pytest.fixture(scope="module", autouse=True)
def _worlds():
    """Fit both worlds once (cached per process) so that every env below is cheap to make."""
    for name in SCENARIOS:
        build_world(name)


def make(name: str = "high_cov", **kw) -> PassageEnv:
    env = PassageEnv(name, **kw)
    env.reset(seed=0)
    return env


def step(env: PassageEnv, action=(0.0, 0.0)):
    return env.step(np.asarray(action, dtype=np.float32))


def goto(env: PassageEnv, target, max_steps: int = 200, tol: float = 1e-9):
    """Hold the correction at ``target`` until the robot is there (or the episode ends). Returns the steps'
    (reward, terminated, truncated, info, robot position after the step) tuples."""
    env.set_correction(np.asarray(target, dtype=np.float64))
    out = []
    for _ in range(max_steps):
        _, r, te, tr, info = step(env)
        out.append((r, te, tr, info, env.robot.copy()))
        if te or tr or np.max(np.abs(env.robot - np.asarray(target))) <= tol:
            break
    return out


def hold_until(env: PassageEnv, t: int) -> None:
    """Keep the robot parked at the start (a correction there) until env.t == t."""
    env.set_correction(np.asarray(env.scenario.start))
    while env.t < t:
        step(env)
    env.set_correction(None)


def check_reward_terms(env: PassageEnv, r: float, info: dict, robot: np.ndarray | None = None) -> None:
    """Eq. 7-11 from the info and the model, independently of the env's own bookkeeping. ``robot``: the
    position after that step (default: the env's current one)."""
    robot = env.robot if robot is None else robot
    mean = np.asarray(env.world.model.grid_mean)[info["t"]]
    dp = np.asarray(info["desired"]) - mean
    assert info["r_a"] == pytest.approx(-10.0 * float(dp @ dp), rel=1e-12, abs=1e-15)
    assert info["r_o"] in (0.0, -10.0) and info["r_p"] in (0.0, -10.0) and info["r_T"] in (0.0, 200.0)
    assert (info["r_o"] == -10.0) == info["in_obstacle"]
    assert (info["r_p"] == -10.0) == info["blocked"]
    assert (info["r_T"] == 200.0) == info["success"]
    assert r == pytest.approx(info["r_a"] + info["r_o"] + info["r_p"] + info["r_T"], rel=1e-12, abs=1e-12)
    if env.scenario.obstacle is None:
        assert info["r_o"] == 0.0 and not info["in_obstacle"]
    else:
        ob = env.scenario.obstacle
        inside = np.hypot(*(robot - np.asarray(ob.center))) < ob.radius
        assert inside == info["in_obstacle"]


# ============================================================================ Gymnasium API
@pytest.mark.parametrize("name", SCENARIOS)
def test_check_env(name):
    env = gym.make(ENV_ID, scenario=name)  # through make: the env has a spec, so render modes get checked too
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings count as failures
        # (pygame, first imported by the render check, warns about setuptools' pkg_resources where setuptools < 81,
        # which the test extra's lerobot-dataset pins: not the environment's warning; khgrl/__init__.py says more)
        warnings.filterwarnings("ignore", message="pkg_resources is deprecated as an API", category=UserWarning)
        check_env(env.unwrapped)


@pytest.mark.parametrize("name", SCENARIOS)
def test_gym_make(name):
    env = gym.make(ENV_ID, scenario=name)
    obs, info = env.reset(seed=0)
    assert env.unwrapped.scenario.name == name
    assert obs.shape == (5,) and obs.dtype == np.float32 and env.observation_space.contains(obs)
    obs, r, te, tr, info = env.step(env.action_space.sample())
    assert isinstance(r, float) and not te and not tr
    assert env.observation_space.contains(obs)
    env.close()


def test_reset_is_deterministic_and_observation_layout():
    env = PassageEnv("high_cov")
    o1, info = env.reset(seed=1)
    o2, _ = env.reset(seed=2)
    np.testing.assert_array_equal(o1, o2)  # start_noise = 0: deterministic start
    assert info == {"phase": 0.0}
    sc = env.scenario
    mean0 = env.mapping.mean(0)
    np.testing.assert_allclose(o1, np.r_[sc.start, 0.0, np.asarray(sc.start) - mean0].astype(np.float32), atol=1e-7)
    obs, _, _, _, _ = step(env, [0.3, -0.2])
    np.testing.assert_allclose(obs[:2], env.robot, atol=1e-7)
    assert obs[2] == pytest.approx(env.mapping.phases[1])
    np.testing.assert_allclose(obs[3:], np.clip(env.robot - env.mapping.mean(1), -1, 1), atol=1e-7)


def test_start_noise_is_seeded():
    env = PassageEnv("high_cov", start_noise=0.01)
    a, _ = env.reset(seed=5)
    b, _ = env.reset(seed=5)
    c, _ = env.reset(seed=6)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.all(np.abs(a[:2] - np.asarray(env.scenario.start)) <= 0.01 + 1e-7)


def test_bad_render_mode():
    with pytest.raises(ValueError):
        PassageEnv("high_cov", render_mode="ascii")


def test_unknown_scenario():
    with pytest.raises(ValueError):
        PassageEnv("nope")


@pytest.mark.parametrize("bad", [[np.nan, 0.0], [0.0, np.inf], [0.1, 0.2, 0.3], [0.5], 0.5, []])
def test_bad_actions_raise(bad):
    env = make()
    with pytest.raises(ValueError):
        env.step(np.asarray(bad, dtype=np.float64))
    assert env.t == 0  # nothing happened


@pytest.mark.parametrize("bad", [[np.nan, 0.5], [0.5, -np.inf], [0.1, 0.2, 0.3], [0.5], 0.5])
def test_bad_corrections_raise(bad):
    env = make()
    with pytest.raises(ValueError):
        env.set_correction(np.asarray(bad, dtype=np.float64))
    assert not env.intervening


def test_actions_outside_box_are_clipped():
    a = make()
    b = make()
    for _ in range(30):
        step(a, [5.0, -7.0])
        step(b, [1.0, -1.0])
    np.testing.assert_array_equal(a.robot, b.robot)


def test_rgb_array_render():
    env = PassageEnv("high_cov", render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(3):
        step(env, [0.5, 0.5])
    img = env.render()
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8
    assert img.ndim == 3 and img.shape[2] == 3 and img.shape[0] > 0 and img.shape[1] > 0
    assert img.std() > 0  # not a blank frame
    env.close()


def test_render_without_mode_returns_none():
    env = make()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert env.render() is None


# ============================================================================ rewards (eqs. 7-11)
def test_action_cost_every_step_kgrl():
    env = make("high_cov")
    rng = np.random.default_rng(0)
    for _ in range(120):
        _, r, te, tr, info = step(env, rng.uniform(-1, 1, 2))
        check_reward_terms(env, r, info)
        assert not info["intervened"]
        if te or tr:
            break


def test_obstacle_cost_when_inside():
    """Drive the robot through the first gap into the obstacle with corrections."""
    env = make("high_cov")
    sc = env.scenario
    wall = sc.walls[0]
    gap_y = wall.gap_center
    seen_inside = False
    for target in [(wall.x - 0.05, gap_y), (wall.x + 0.05, gap_y), sc.obstacle.center]:
        for r, te, tr, info, robot in goto(env, target):
            check_reward_terms(env, r, info, robot)
            assert not te and not tr
            if info["in_obstacle"]:
                seen_inside = True
                assert info["r_o"] == -10.0
                assert info["r_p"] == 0.0 and info["r_T"] == 0.0
    assert seen_inside
    np.testing.assert_allclose(env.robot, sc.obstacle.center, atol=1e-12)
    # sitting at the centre: every step costs r_o
    _, r, _, _, info = step(env)
    assert info["r_o"] == -10.0 and info["in_obstacle"]
    # the action cost is that of the held correction
    dp = np.asarray(sc.obstacle.center) - env.mapping.mean(info["t"])
    assert r == pytest.approx(-10.0 * dp @ dp - 10.0, rel=1e-12)


def test_passage_cost_and_failure_after_blocked_limit():
    """Zero actions in high_cov: the mean misses the first gap, the robot presses against the wall."""
    env = make("high_cov")
    wall = env.scenario.walls[0]
    consecutive = 0
    for _ in range(env.horizon):
        _, r, te, tr, info = step(env)
        check_reward_terms(env, r, info)
        consecutive = consecutive + 1 if info["blocked"] else 0
        if info["blocked"]:
            assert info["r_p"] == -10.0
            assert env.robot[0] == pytest.approx(wall.x - 1e-4, abs=1e-12)
            assert not (wall.gap_lo < env.robot[1] < wall.gap_hi)
        else:
            assert info["r_p"] == 0.0
        if consecutive < env.blocked_limit:
            assert not te and not info["failure"]
        if te or tr:
            break
    assert env.blocked_limit == 20
    assert consecutive == 20
    assert te and not tr and info["failure"] and not info["success"]
    assert info["r_T"] == 0.0


@pytest.mark.parametrize("limit", [1, 5])
def test_blocked_limit_is_configurable(limit):
    env = make("high_cov", blocked_limit=limit)
    n_blocked = 0
    for _ in range(env.horizon):
        _, _, te, tr, info = step(env)
        n_blocked += int(info["blocked"])
        if te or tr:
            break
    assert te and info["failure"] and n_blocked == limit


def test_blocked_counter_resets_when_free():
    env = make("high_cov")
    wall = env.scenario.walls[0]
    # press against the wall 19 times, then step away, then press again: no failure
    env.set_correction(np.array([wall.x + 0.2, 0.3]))
    goto(env, (wall.x - 0.005, 0.3))
    env.set_correction(np.array([wall.x + 0.2, 0.3]))
    blocked = 0
    while blocked < env.blocked_limit - 1:
        _, _, te, _, info = step(env)
        assert not te
        blocked += int(info["blocked"])
    _, te, _, info, _ = goto(env, (wall.x - 0.005, 0.3))[-1]  # one free step back
    assert not te and not info["blocked"] and env.blocked_steps == 0
    env.set_correction(np.array([wall.x + 0.2, 0.3]))
    for _ in range(env.blocked_limit - 1):
        _, _, te, _, info = step(env)
        assert not te
    _, _, te, _, info = step(env)
    assert te and info["failure"]


def test_success_reward_and_termination():
    """Corrections along a safe path through both gaps to the goal (high_cov)."""
    env = make("high_cov")
    sc = env.scenario
    w1, w2 = sc.walls
    path = [
        (w1.x - 0.05, w1.gap_center),
        (w1.x + 0.05, w1.gap_center),
        (w2.x - 0.05, w2.gap_center),
        (w2.x + 0.05, w2.gap_center),
        sc.goal,
    ]
    ended = None
    for target in path:
        for r, te, tr, info, robot in goto(env, target):
            check_reward_terms(env, r, info, robot)
            assert info["r_o"] == 0.0 and info["r_p"] == 0.0
            if te or tr:
                ended = (r, te, tr, info)
                break
        if ended:
            break
    assert ended is not None
    r, te, tr, info = ended
    assert te and not tr and info["success"] and not info["failure"]
    assert info["r_T"] == 200.0
    assert np.hypot(*(env.robot - np.asarray(sc.goal))) <= sc.goal_radius
    assert r == pytest.approx(200.0 + info["r_a"])


def test_truncation_at_horizon_then_step_raises():
    """Corrections that keep the robot parked at the start: neither goal nor wall, so truncation at T."""
    env = make("high_cov")
    env.set_correction(np.asarray(env.scenario.start))
    assert env.horizon == 400
    for k in range(1, env.horizon + 1):
        _, r, te, tr, info = step(env)
        check_reward_terms(env, r, info)
        assert not te
        assert tr == (k == env.horizon)
    assert env.t == 400
    with pytest.raises(RuntimeError):
        step(env)
    # reset makes it usable again
    env.reset()
    step(env)


def test_step_after_termination_raises():
    """BUG: the docstring says step() after the episode ended raises, but after a *terminated* episode
    (success or failure before T) the env keeps stepping (it only checks t >= T)."""
    env = make("high_cov")
    for _ in range(env.horizon):
        _, _, te, tr, info = step(env)
        if te or tr:
            break
    assert te and info["failure"] and env.t < env.horizon
    with pytest.raises(RuntimeError):
        step(env)


@pytest.mark.parametrize("seed", [0, 1])
def test_low_cov_never_has_obstacle_cost(seed):
    env = make("low_cov")
    rng = np.random.default_rng(seed)
    for k in range(env.horizon):
        if k % 25 == 0:
            env.set_correction(rng.uniform(0, 1, 2) if rng.uniform() < 0.5 else None)
        _, r, te, tr, info = step(env, rng.uniform(-1, 1, 2))
        check_reward_terms(env, r, info)
        assert info["r_o"] == 0.0
        if te or tr:
            break


# ============================================================================ physics
def _crossings(prev: np.ndarray, new: np.ndarray, walls):
    """The walls whose line x = wall.x the segment prev -> new reaches or crosses from one side, with the
    y where it does."""
    for wall in walls:
        d0, d1 = prev[0] - wall.x, new[0] - wall.x
        if d0 * d1 < 0 or (d1 == 0 and d0 != 0) or (d0 == 0 and d1 != 0):
            frac = d0 / (d0 - d1)
            yield wall, prev[1] + frac * (new[1] - prev[1])


@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.parametrize("seed", range(4))
def test_walls_only_passable_through_gaps_and_speed_limit(name, seed):
    """Random actions and random held corrections (many aimed across the walls, some at the gaps). A huge
    blocked_limit keeps every episode running for the full T steps."""
    env = make(name, blocked_limit=10**6)
    sc = env.scenario
    rng = np.random.default_rng(seed)
    prev = env.robot.copy()
    n_blocked = n_crossed = 0
    for k in range(env.horizon):
        if k % 15 == 0:
            u = rng.uniform()
            if u < 0.3:
                env.set_correction(None)
            elif u < 0.6:
                env.set_correction(rng.uniform(-0.1, 1.1, 2))  # anywhere, also outside the workspace
            else:
                wall = sc.walls[rng.integers(len(sc.walls))]
                side = 1.0 if prev[0] < wall.x else -1.0
                y = rng.uniform(wall.gap_lo, wall.gap_hi) if u < 0.8 else rng.uniform(0, 1)
                env.set_correction(np.array([wall.x + side * rng.uniform(0.01, 0.1), y]))
        _, r, te, tr, info = step(env, rng.uniform(-1, 1, 2))
        new = env.robot.copy()
        assert np.hypot(*(new - prev)) <= env.speed + 1e-12
        assert np.all(new >= 0.0) and np.all(new <= 1.0)
        for wall, y in _crossings(prev, new, sc.walls):
            n_crossed += 1
            assert wall.gap_lo < y < wall.gap_hi, f"step {k}: crossed x = {wall.x} at y = {y} outside the gap"
        for wall in sc.walls:
            if new[0] == wall.x:
                assert wall.gap_lo < new[1] < wall.gap_hi, f"step {k}: robot inside the wall at {new}"
        if info["blocked"]:
            n_blocked += 1
            assert min(abs(new[0] - w.x) for w in sc.walls) == pytest.approx(1e-4, abs=1e-12)
        check_reward_terms(env, r, info)
        prev = new
        if te or tr:
            break
    assert tr and env.t == env.horizon
    assert n_blocked > 0  # the walls were really tested (n_crossed: gap passages, usually a few)


def test_robot_cannot_slide_along_wall_out_of_the_gap():
    """BUG: a robot that lands exactly on a wall's line inside the gap (a correction at x = wall.x) is no
    longer stopped by that wall: _segment_blocked only counts moves that start off the line. It can slide
    along x = wall.x into the wall body and leave on the far side at any y. (Pressing along the line is
    blocked, so the blocked-step limit is raised to keep the episode running.)"""
    env = make("high_cov", blocked_limit=10_000)
    wall = env.scenario.walls[0]
    goto(env, (wall.x - 0.07, wall.gap_center))
    goto(env, (wall.x, wall.gap_center))  # into the gap, exactly on the wall's line: legal
    np.testing.assert_allclose(env.robot, [wall.x, wall.gap_center], atol=1e-12)
    goto(env, (wall.x, 0.40), max_steps=30)  # along the line, out of the gap
    on_line = env.robot.copy()
    goto(env, (wall.x + 0.08, 0.40), max_steps=20)
    assert not (on_line[0] == wall.x and not wall.gap_lo < on_line[1] < wall.gap_hi), (
        f"robot inside the wall body at {on_line} (gap {wall.gap_lo}..{wall.gap_hi})"
    )
    trail = np.array(env.trail)
    for a, b in zip(trail[:-1], trail[1:]):  # every passage of the wall line happened inside the gap
        if (a[0] - wall.x) * (b[0] - wall.x) <= 0 and a[0] != b[0]:
            y = a[1] + (wall.x - a[0]) / (b[0] - a[0]) * (b[1] - a[1])
            assert wall.gap_lo < y < wall.gap_hi, f"crossed x = {wall.x} at y = {y} outside the gap"
    assert env.robot[0] > wall.x  # it did get through, by the gap


def test_speed_limit_and_straight_motion():
    env = make("high_cov", speed=0.02)
    env.set_correction(np.array([0.08, 0.9]))
    prev = env.robot.copy()
    step(env)
    np.testing.assert_allclose(env.robot - prev, [0.0, 0.02], atol=1e-15)


# ============================================================================ the intervention path (eq. 6)
@pytest.fixture()
def high_at_200():
    env = make("high_cov")
    hold_until(env, 200)
    return env


def test_intervention_action_and_round_trip(high_at_200):
    env = high_at_200
    t = env.t
    model = env.world.model
    mean = np.asarray(model.grid_mean)[t]
    p_h = mean + np.array([0.0, 0.05])
    env.set_correction(p_h)
    assert env.intervening
    _, r, _, _, info = step(env, [0.9, -0.9])  # the policy's action is overridden
    assert info["t"] == t and info["intervened"] and not info["projected"]
    assert not info["clipped"], "test setting: the human's action should fit in [-1, 1]"
    L = np.asarray(info["scale"])
    np.testing.assert_array_equal(L, [20.0, 20.0])
    xi_ref = np.linalg.solve(np.asarray(model.grid_projector)[t], p_h - mean)
    np.testing.assert_allclose(info["xi_h"], xi_ref, rtol=1e-10, atol=1e-12)
    expected = np.clip(info["xi_h"] / L, -1.0, 1.0)
    np.testing.assert_array_equal(info["raw_action"], info["xi_h"] / L)
    assert info["action"].dtype == np.float32
    np.testing.assert_array_equal(info["action"], expected.astype(np.float32))
    np.testing.assert_array_equal(info["desired"], p_h)
    check_reward_terms(env, r, info)
    # P_h -> a_h -> P_t: the forward KGRL map reproduces the correction, with no constraint active
    p_t, xi = env.mapping.act(t, info["raw_action"], L)
    assert model.step_info.active_rows == 0
    np.testing.assert_allclose(p_t, p_h, rtol=0, atol=1e-9)
    np.testing.assert_allclose(xi, info["xi_h"], rtol=1e-12)
    # the stored float32 action reproduces it up to float32 rounding of a
    p_32, _ = env.mapping.act(t, info["action"], L)
    bound = np.linalg.norm(np.asarray(model.grid_projector)[t], 2) * L.max() * 2 * np.finfo(np.float32).eps
    assert np.max(np.abs(p_32 - p_h)) <= bound


def test_intervention_clipped_in_low_cov():
    env = make("low_cov")
    hold_until(env, 230)
    t = env.t
    mean = env.mapping.mean(t)
    p_h = mean + np.array([0.0, 0.06])  # toward the second gap, far beyond what L = 15 reaches there
    env.set_correction(p_h)
    _, _, _, _, info = step(env)
    assert info["intervened"] and info["clipped"] and not info["projected"]
    raw = info["xi_h"] / info["scale"]
    assert np.max(np.abs(raw)) > 1.0
    np.testing.assert_array_equal(info["raw_action"], raw)
    np.testing.assert_array_equal(info["action"], np.clip(raw, -1, 1).astype(np.float32))
    assert np.max(np.abs(info["action"])) == 1.0
    np.testing.assert_array_equal(info["desired"], p_h)  # the robot still goes to P_h itself


@pytest.mark.parametrize("p", [(1.5, -0.2), (-3.0, 0.5), (0.5, 1.0), (0.0, 0.0)])
def test_correction_outside_workspace_projected(p):
    env = make("high_cov")
    m = env.scenario.workspace_margin
    env.set_correction(np.array(p))
    _, r, _, _, info = step(env)
    assert info["intervened"] and info["projected"]
    np.testing.assert_array_equal(info["desired"], np.clip(p, m, 1 - m))
    assert np.all(info["desired"] >= m) and np.all(info["desired"] <= 1 - m)
    check_reward_terms(env, r, info)


def test_correction_inside_not_projected_and_release():
    env = make("high_cov")
    env.set_correction(np.array([0.1, 0.55]))
    _, _, _, _, info = step(env)
    assert info["intervened"] and not info["projected"]
    env.set_correction(None)
    assert not env.intervening
    _, _, _, _, info = step(env, [0.25, -0.5])
    assert not info["intervened"] and not info["clipped"] and not info["projected"]
    np.testing.assert_array_equal(info["action"], np.array([0.25, -0.5], dtype=np.float32))
    assert "xi_h" not in info


def test_reset_releases_correction():
    env = make("high_cov")
    env.set_correction(np.array([0.1, 0.55]))
    env.reset()
    assert not env.intervening


def test_kgrl_step_matches_mapping():
    """Without a correction, the desired position is exactly KGRLMapping.act of the (clipped) action."""
    env = make("high_cov")
    ref = KGRLMapping(env.world.model, ScaleModel(20.0, dim=2))
    rng = np.random.default_rng(3)
    for t in range(60):
        a = rng.uniform(-1.2, 1.2, 2)
        _, _, _, _, info = step(env, a)
        p, xi = ref.act(t, np.clip(a.astype(np.float32).astype(np.float64), -1, 1), np.array([20.0, 20.0]))
        np.testing.assert_allclose(info["desired"], p, atol=1e-12)
        np.testing.assert_allclose(info["xi"], xi, atol=1e-12)
