"""The passage-world scenario design (common/tasks/passage/scenarios.py), proven from the fitted model itself.

Everything is computed from ``khgrl.common.tasks.passage.env.build_world(name)``: the LC-NS-KMP's grid mean eta0_n and
projector N_n, and the scenario's geometry. The reachable deviation with exploration scale L at grid
point n is max over the corners a of [-1, 1]^2 of ||N_n (L (.) a)|| (the policy action is bounded by 1
per dimension; the maximum of a convex function over the box is at a corner).

These are the acceptance criteria of the scenario design (paper Section IV):

* high_cov (A): with L = 20 exploration reaches the obstacle (collisions and avoidance both possible)
  and both gaps;
* low_cov (B): with L = 15 the deviation at the second wall falls short of its gap (KGRL cannot pass),
  while the L the GPR learns from one scripted-human intervention reaches it.
"""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.tasks.passage.env import PassageEnv, build_world
from khgrl.common.tasks.passage.scenarios import SCENARIOS, get_scenario, make_demos
from khgrl.human_bridge.scripted import HumanCorrectionWrapper, ScriptedHuman, ScriptedHumanConfig

CORNERS = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])


def reachable(projector: np.ndarray, L: np.ndarray) -> np.ndarray:
    """(N,) max over the action box's corners of ||N_n (L_n (.) a)||; L is (O,) or (N, O)."""
    L = np.broadcast_to(np.asarray(L, dtype=np.float64), (projector.shape[0], projector.shape[2]))
    xi = L[:, None, :] * CORNERS[None, :, :]  # (N, 4, O)
    dev = np.einsum("nij,nkj->nki", projector, xi)
    return np.linalg.norm(dev, axis=2).max(axis=1)


def reachable_eig(projector: np.ndarray, L: float) -> np.ndarray:
    """(N,) upper bound lambda_max(N_n) * L * sqrt(2) (N_n symmetric PSD)."""
    return np.linalg.eigvalsh(projector)[:, -1] * L * np.sqrt(2.0)


def phase_at_wall(mean: np.ndarray, wall_x: float, tol: float = 0.03) -> np.ndarray:
    idx = np.flatnonzero(np.abs(mean[:, 0] - wall_x) <= tol)
    assert idx.size > 0, f"the mean never comes within {tol} of x = {wall_x}"
    return idx


def distance_to_gap(y: np.ndarray, wall) -> np.ndarray:
    """Distance in y from y to the nearest point of the open gap (0 inside it)."""
    inside = (y > wall.gap_lo) & (y < wall.gap_hi)
    return np.where(inside, 0.0, np.minimum(np.abs(y - wall.gap_lo), np.abs(y - wall.gap_hi)))


@pytest.fixture(scope="module")
def high():
    return build_world("high_cov")


@pytest.fixture(scope="module")
def low():
    return build_world("low_cov")


# ------------------------------------------------------------------------------------ sanity of the helpers
def test_reachable_matches_eigen_bound(high, low):
    for w in (high, low):
        P = np.asarray(w.model.grid_projector)
        L = w.scenario.default_scale
        exact = reachable(P, L)
        bound = reachable_eig(P, L)
        assert np.all(exact <= bound + 1e-12)
        # corners of the box cover at least the largest eigen direction projected onto a corner: >= bound / sqrt(2)
        assert np.all(exact >= bound / np.sqrt(2.0) - 1e-12)


def test_world_shapes_and_defaults(high, low):
    for w, name, L0 in ((high, "high_cov", 20.0), (low, "low_cov", 15.0)):
        assert w.scenario is get_scenario(name)
        assert w.scenario.default_scale == L0
        n = w.demos.shape[1]
        assert np.asarray(w.model.grid_mean).shape == (n, 2)
        assert np.asarray(w.model.grid_projector).shape == (n, 2, 2)
        P = np.asarray(w.model.grid_projector)
        np.testing.assert_allclose(P, np.swapaxes(P, 1, 2), atol=1e-12)
        assert np.all(np.linalg.eigvalsh(P) > 0)
    assert high.scenario.obstacle is not None and low.scenario.obstacle is None
    assert not high.scenario.learn_scale and low.scenario.learn_scale


def test_build_world_is_cached():
    assert build_world("high_cov") is build_world("high_cov")


# ------------------------------------------------------------------------------------ high_cov (A)
def test_high_cov_obstacle_reachable_with_L20(high):
    sc = high.scenario
    mean = np.asarray(high.model.grid_mean)
    P = np.asarray(high.model.grid_projector)
    ob = sc.obstacle
    idx = np.flatnonzero(np.abs(mean[:, 0] - ob.center[0]) <= ob.radius)
    assert idx.size > 0
    reach = reachable(P[idx], 20.0)
    # the mean passes through (or right next to) the obstacle, and exploration reaches further than its radius:
    # the robot can both collide and avoid it
    assert reach.min() > ob.radius, (reach.min(), ob.radius)
    dist_center = np.linalg.norm(mean[idx] - np.asarray(ob.center), axis=1)
    # avoidance is possible: the reachable deviation exceeds the depth needed to leave the disc from the mean
    assert np.all(reach > ob.radius - dist_center)
    # collision is possible: the disc is within reach of the mean at every phase of it
    assert np.all(reach > dist_center - ob.radius)
    assert np.any(dist_center < ob.radius), "the mean should cross the obstacle (collisions likely without help)"


@pytest.mark.parametrize("k", [0, 1])
def test_high_cov_gaps_reachable_with_L20(high, k):
    sc = high.scenario
    wall = sc.walls[k]
    mean = np.asarray(high.model.grid_mean)
    idx = phase_at_wall(mean, wall.x)
    reach = reachable(np.asarray(high.model.grid_projector)[idx], 20.0)
    need = distance_to_gap(mean[idx, 1], wall)
    assert np.all(need > 0), "the mean should not pass the gap by itself (RL must learn the deviation)"
    assert np.all(reach >= need), (reach.min(), need.max())


# ------------------------------------------------------------------------------------ low_cov (B)
def test_low_cov_first_gap_on_the_mean(low):
    wall = low.scenario.walls[0]
    mean = np.asarray(low.model.grid_mean)
    idx = phase_at_wall(mean, wall.x)
    assert np.all(distance_to_gap(mean[idx, 1], wall) == 0.0)


def test_low_cov_kgrl_cannot_reach_second_gap_with_L15(low):
    wall = low.scenario.walls[1]
    mean = np.asarray(low.model.grid_mean)
    idx = phase_at_wall(mean, wall.x)
    reach = reachable(np.asarray(low.model.grid_projector)[idx], 15.0)
    need = distance_to_gap(mean[idx, 1], wall)
    assert np.all(need > 0)
    assert reach.max() < need.min(), (reach.max(), need.min())
    # also the (looser) eigenvalue bound
    assert reachable_eig(np.asarray(low.model.grid_projector)[idx], 15.0).max() < need.min()


@pytest.fixture(scope="module")
def learned_low():
    """One low_cov episode with zero policy actions and the scripted human in episode 1; L refit from its
    intervention exactly as KhGRL does (on_release -> update_scale)."""
    env = PassageEnv("low_cov")
    segments: list[list[dict]] = []
    wrapped = HumanCorrectionWrapper(
        env,
        ScriptedHuman("low_cov", ScriptedHumanConfig(episodes=(1,))),
        on_release=lambda seg: segments.append(list(seg)),
    )
    wrapped.reset(seed=0)
    done = False
    steps = 0
    while not done:
        _, _, terminated, truncated, _ = wrapped.step(np.zeros(2))
        done = terminated or truncated
        steps += 1
    assert segments, "the scripted human never intervened"
    xi = np.concatenate([np.array([d["xi_h"] for d in seg]) for seg in segments])
    phases = np.concatenate([np.array([d["phase"] for d in seg]) for seg in segments])
    env.mapping.update_scale(xi, phases)
    return env, xi, phases


def test_low_cov_learned_scale_reaches_second_gap(low, learned_low):
    env, xi, phases = learned_low
    wall = low.scenario.walls[1]
    mean = np.asarray(low.model.grid_mean)
    idx = phase_at_wall(mean, wall.x)
    # the intervention covered the second wall's phase
    assert phases.min() <= env.mapping.phases[idx].min() and phases.max() >= env.mapping.phases[idx].max()
    L_learned = np.stack([env.mapping.scale_at(int(n)) for n in idx])
    reach = reachable(np.asarray(low.model.grid_projector)[idx], L_learned)
    need = distance_to_gap(mean[idx, 1], wall)
    assert np.all(reach >= need), (reach.min(), need.max())
    # and the default L did not: the GPR made the difference
    assert np.all(L_learned > 15.0)


def test_low_cov_learned_scale_stays_default_far_from_data(learned_low):
    env, _, phases = learned_low
    far = np.flatnonzero((env.mapping.phases < phases.min() - 0.2) | (env.mapping.phases > phases.max() + 0.2))
    assert far.size > 0
    table = np.stack([env.mapping.scale_at(int(n)) for n in far])
    np.testing.assert_allclose(table, 15.0, rtol=1e-3)  # 5 GP length scales away


# ------------------------------------------------------------------------------------ generated demonstrations
@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_demos_shape_and_endpoints(name):
    sc = get_scenario(name)
    demos = make_demos(name)
    assert demos.shape == (9, 400, 2)
    assert demos.dtype == np.float64 and np.all(np.isfinite(demos))
    np.testing.assert_allclose(demos[:, 0], np.broadcast_to(sc.start, (9, 2)), atol=1e-9)
    assert np.all(np.linalg.norm(demos[:, -1] - np.asarray(sc.goal), axis=1) < sc.goal_radius)
    # inside the unit square
    assert demos.min() >= 0.0 and demos.max() <= 1.0


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_demos_deterministic_per_seed(name):
    np.testing.assert_array_equal(make_demos(name, seed=3), make_demos(name, seed=3))
    assert not np.allclose(make_demos(name, seed=0), make_demos(name, seed=1))


def test_demos_accepts_scenario_object_and_sizes():
    sc = get_scenario("low_cov")
    np.testing.assert_array_equal(make_demos(sc, seed=2), make_demos("low_cov", seed=2))
    assert make_demos(sc, n_demos=3, n_steps=50).shape == (3, 50, 2)


def test_demos_bad_arguments():
    with pytest.raises(ValueError):
        make_demos("high_cov", n_demos=1)
    with pytest.raises(ValueError):
        make_demos("high_cov", n_steps=5)
    with pytest.raises(ValueError, match="unknown scenario"):
        get_scenario("nope")


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_demos_spread_follows_design(name):
    """The demos fan out where the design says: the widest spread in the middle, none at the ends."""
    sc = get_scenario(name)
    demos = make_demos(name)
    spread = demos[:, :, 1].max(axis=0) - demos[:, :, 1].min(axis=0)
    assert spread[0] < 1e-9 and spread[-1] < 1e-3
    peak = max(h for _, h in sc.spread_knots)
    assert spread.max() > peak  # 2 * half_width * (1 +- wobble) > half_width


def test_human_waypoints_pass_through_gaps_and_avoid_obstacle():
    for sc in SCENARIOS.values():
        way = np.asarray(sc.human_waypoints)
        xs = np.linspace(way[0, 0], way[-1, 0], 2001)
        ys = np.interp(xs, way[:, 0], way[:, 1])
        for wall in sc.walls:
            y = float(np.interp(wall.x, way[:, 0], way[:, 1]))
            assert wall.gap_lo < y < wall.gap_hi, (sc.name, wall, y)
        if sc.obstacle is not None:
            d = np.hypot(xs - sc.obstacle.center[0], ys - sc.obstacle.center[1])
            assert d.min() > sc.obstacle.radius
