"""The KGRL mapping (eq. 5) and its inverse (eq. 6) on the passage worlds' LC-NS-KMP (common/kmp/mapping.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from khgrl.common.kmp.mapping import KGRLMapping, scale, unscale
from khgrl.common.kmp.scale import ScaleConfig, ScaleModel
from khgrl.common.tasks.passage.env import build_world

HYP = settings(max_examples=40, deadline=None)
finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
positive = st.floats(1e-3, 1e4, allow_nan=False, allow_infinity=False)


@pytest.fixture(scope="module")
def world():
    return build_world("high_cov")


@pytest.fixture(scope="module")
def low_world():
    return build_world("low_cov")


@pytest.fixture()
def mapping(world):
    return KGRLMapping(world.model, ScaleModel(20.0, dim=2))


# ------------------------------------------------------------------------------------ scale / unscale
@HYP
@given(a=st.tuples(finite, finite), L=st.tuples(positive, positive))
def test_unscale_scale_inverse(a, L):
    a, L = np.array(a), np.array(L)
    np.testing.assert_allclose(scale(unscale(a, L), L), a, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(unscale(scale(a, L), L), a, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(unscale(a, L), L * a)


# ------------------------------------------------------------------------------------ act / intervene
def test_act_is_eq5_when_unconstrained(mapping, world):
    P = np.asarray(world.model.grid_projector)
    mean = np.asarray(world.model.grid_mean)
    L = np.array([20.0, 20.0])
    for t in range(0, mapping.horizon, 13):
        a = np.array([0.4, -0.7])
        p, xi = mapping.act(t, a, L)
        np.testing.assert_array_equal(xi, L * a)
        assert world.model.step_info.active_rows == 0
        np.testing.assert_allclose(p, mean[t] + P[t] @ xi, atol=1e-14)


def test_act_zero_action_gives_mean(mapping, world):
    mean = np.asarray(world.model.grid_mean)
    for t in (0, 100, 250, 399):
        p, _ = mapping.act(t, np.zeros(2), np.array([20.0, 20.0]))
        np.testing.assert_allclose(p, mean[t], atol=1e-14)
        np.testing.assert_array_equal(mapping.mean(t), mean[t])


@pytest.mark.parametrize("which", ["high", "low"])
def test_act_intervene_round_trip_on_grid(which, world, low_world):
    w = world if which == "high" else low_world
    m = KGRLMapping(w.model, ScaleModel(w.scenario.default_scale, dim=2))
    L = np.full(2, w.scenario.default_scale)
    rng = np.random.default_rng(0)
    for t in range(0, m.horizon, 5):
        a = rng.uniform(-1, 1, 2)
        p, _ = m.act(t, a, L)
        iv = m.intervene(t, p, L)
        np.testing.assert_allclose(iv.raw_action, a, atol=1e-8)
        assert not iv.clipped
        np.testing.assert_allclose(iv.action, a, atol=1e-8)
        np.testing.assert_allclose(iv.xi, L * a, rtol=1e-7, atol=1e-6)
        # and back: a_h -> P_t reproduces the position
        p2, _ = m.act(t, iv.raw_action, L)
        np.testing.assert_allclose(p2, p, atol=1e-9)


def test_intervene_clips_and_counts(low_world):
    m = KGRLMapping(low_world.model, ScaleModel(15.0, dim=2))
    t = 230
    p_h = m.mean(t) + np.array([0.0, 0.06])
    L = np.array([15.0, 15.0])
    iv = m.intervene(t, p_h, L)
    assert iv.clipped
    np.testing.assert_array_equal(iv.raw_action, iv.xi / L)
    np.testing.assert_array_equal(iv.action, np.clip(iv.raw_action, -1, 1))
    assert np.max(np.abs(iv.raw_action)) > 1
    # eq. 6: N_t xi_h = P_h - eta0_t
    np.testing.assert_allclose(np.asarray(low_world.model.grid_projector)[t] @ iv.xi, p_h - m.mean(t), atol=1e-12)


def _edge_case(world):
    """t = 280, P_h on the workspace box's top edge: the forward map of xi_h = N^-1 (P_h - eta0) pushes the
    trajectory out of the box nearby, so a constraint is active and eq. 6 needs the constraint term."""
    m = KGRLMapping(world.model, ScaleModel(20.0, dim=2))
    t = 280
    p_h = np.array([m.mean(t)[0], 1.0 - world.scenario.workspace_margin])
    return m, t, p_h, np.array([1e4, 1e4])  # L large enough that nothing is clipped


def test_intervene_with_active_constraints_converges(world):
    m, t, p_h, L = _edge_case(world)
    xi0 = world.model.grid_invert(t, p_h)  # plain eq. 6 (alpha = 0)
    p0, _ = m.act(t, xi0 / L, L)
    assert world.model.step_info.active_rows > 0
    assert np.max(np.abs(p0 - p_h)) > 1e-4  # eq. 6 alone misses P_h here
    iv = m.intervene(t, p_h, L)  # accounts for the active constraints (Newton on the piecewise-affine map)
    p, _ = m.act(t, iv.raw_action, L)
    np.testing.assert_allclose(p, p_h, atol=1e-7)


def test_intervene_with_active_constraints_default_iterations():
    """intervene() promises that the forward map reproduces P_h when constraints are active (a fixed-point
    correction used to stop ~3.5e-4 away; now Newton steps on the piecewise-affine map)."""
    m, t, p_h, L = _edge_case(build_world("high_cov"))
    iv = m.intervene(t, p_h, L)
    p, _ = m.act(t, iv.raw_action, L)
    np.testing.assert_allclose(p, p_h, atol=1e-6)


# ------------------------------------------------------------------------------------ band / scale table
def test_band_shape_and_contains_mean(mapping, world):
    band = mapping.band()
    n = mapping.horizon
    mean = np.asarray(world.model.grid_mean)
    assert band.shape == (n, 2, 2)
    lo, hi = band[:, 0], band[:, 1]
    assert np.all(lo <= mean) and np.all(mean <= hi)
    # half-width is |N| L: every corner action lands inside the band
    P = np.asarray(world.model.grid_projector)
    for c in ([1, 1], [1, -1], [-1, 1], [-1, -1]):
        dev = mean + np.einsum("nij,j->ni", P, 20.0 * np.array(c, dtype=float))
        assert np.all(dev >= lo - 1e-12) and np.all(dev <= hi + 1e-12)
    # an explicit L scales it
    band2 = mapping.band(np.array([40.0, 40.0]))
    np.testing.assert_allclose(band2[:, 1] - mean, 2 * (hi - mean), rtol=1e-12)


def test_band_needs_L_for_position_model(world):
    m = KGRLMapping(world.model, ScaleModel(20.0, dim=2, config=ScaleConfig(input="position")))
    with pytest.raises(ValueError):
        m.band()
    assert m.band(np.array([5.0, 5.0])).shape == (m.horizon, 2, 2)
    np.testing.assert_array_equal(m.scale_at(10, np.array([0.3, 0.3])), [20.0, 20.0])


def test_constant_scale_model_keeps_L_constant(mapping):
    """KGRL: no update, the scale table is L0 at every step."""
    table = np.stack([mapping.scale_at(t) for t in range(mapping.horizon)])
    np.testing.assert_array_equal(table, 20.0)
    mapping.refresh_scale()
    np.testing.assert_array_equal(np.stack([mapping.scale_at(t) for t in range(mapping.horizon)]), 20.0)


def test_update_scale_retabulates(low_world):
    m = KGRLMapping(low_world.model, ScaleModel(15.0, dim=2))
    phases = m.phases[200:240]
    m.update_scale(np.tile([300.0, 3000.0], (40, 1)), phases)
    assert m.scale_at(220)[1] > 1000 and m.scale_at(0)[1] == pytest.approx(15.0, rel=1e-6)


def test_scale_model_dim_mismatch(world):
    with pytest.raises(ValueError):
        KGRLMapping(world.model, ScaleModel(20.0, dim=3))
