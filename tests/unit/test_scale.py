"""The learned exploration scale L (common/kmp/scale.py, math.md §5)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from khgrl.common.kmp.scale import ScaleConfig, ScaleModel

HYP = settings(max_examples=30, deadline=None)
GRID = np.linspace(0.0, 1.0, 400)


def cluster(center: float = 0.5, half: float = 0.05, k: int = 30, xi=(100.0, -500.0)):
    phases = np.linspace(center - half, center + half, k)
    return np.tile(np.asarray(xi, dtype=np.float64), (k, 1)), phases


# ------------------------------------------------------------------------------------ prior
def test_default_everywhere_before_update():
    m = ScaleModel(15.0, dim=2)
    assert m.dim == 2 and m.n_points == 0 and m.n_updates == 0
    np.testing.assert_array_equal(m(phase=0.3), [15.0, 15.0])
    assert m(phase=0.3).shape == (2,)
    out = m(phase=np.array([0.0, 0.5, 1.0]))
    assert out.shape == (3, 2)
    np.testing.assert_array_equal(out, 15.0)
    table = m.table(GRID)
    assert table.shape == (400, 2)
    np.testing.assert_array_equal(table, 15.0)


def test_per_dimension_default():
    m = ScaleModel([20.0, 5.0])
    assert m.dim == 2
    np.testing.assert_array_equal(m.table(GRID[:7]), np.tile([20.0, 5.0], (7, 1)))


# ------------------------------------------------------------------------------------ fit
def test_update_near_data_covers_xi_with_margin():
    m = ScaleModel(15.0, dim=2)
    xi, ph = cluster()
    m.update(xi, phase=ph)
    assert m.n_updates == 1 and m.n_points == 30
    target = np.abs(xi[0]) * m.config.margin  # 125, 625
    L = m(phase=0.5)
    np.testing.assert_allclose(L, target, rtol=0.05)
    # across the data the human's action maps to |a| <= 1 (the margin leaves room for GP shrinkage)
    L_data = m(phase=ph)
    assert np.all(np.abs(xi) / L_data <= 1.0)


def test_far_from_data_back_to_default():
    m = ScaleModel(15.0, dim=2)
    xi, ph = cluster(0.5, 0.05)
    m.update(xi, phase=ph)
    for s in (0.0, 0.1, 0.9, 1.0):
        np.testing.assert_allclose(m(phase=s), [15.0, 15.0], rtol=1e-6)


def test_small_xi_floors_at_min_scale():
    m = ScaleModel(15.0, dim=2)
    xi, ph = cluster(xi=(1e-6, 0.0))
    m.update(xi, phase=ph)
    L = m(phase=0.5)
    assert np.all(L >= m.config.min_scale)
    np.testing.assert_allclose(L, m.config.min_scale, rtol=0.15)


def test_update_is_deterministic_and_table_matches_calls():
    xi, ph = cluster()
    a, b = ScaleModel(15.0, dim=2), ScaleModel(15.0, dim=2)
    a.update(xi, phase=ph)
    b.update(xi, phase=ph)
    np.testing.assert_array_equal(a.table(GRID), b.table(GRID))
    np.testing.assert_allclose(a.table(GRID), a(phase=GRID))
    assert a.table(GRID).shape == (400, 2)


def test_empty_update_is_noop():
    m = ScaleModel(15.0, dim=2)
    m.update(np.zeros((0, 2)), phase=np.zeros(0))
    assert m.n_updates == 0 and m.n_points == 0
    np.testing.assert_array_equal(m(phase=0.5), [15.0, 15.0])


@HYP
@given(
    xi=st.lists(
        st.tuples(st.floats(-1e5, 1e5, allow_nan=False), st.floats(-1e5, 1e5, allow_nan=False)), min_size=1, max_size=25
    ),
    phases=st.lists(st.floats(0.0, 1.0, allow_nan=False), min_size=25, max_size=25),
    default=st.floats(0.5, 100.0),
)
def test_always_positive_and_finite(xi, phases, default):
    m = ScaleModel(default, dim=2)
    xi = np.asarray(xi, dtype=np.float64)
    m.update(xi, phase=np.asarray(phases[: len(xi)]))
    table = m.table(GRID)
    assert np.all(np.isfinite(table)) and np.all(table > 0)
    assert np.all(table >= min(m.config.min_scale, default) - 1e-12)


# ------------------------------------------------------------------------------------ serialisation
def test_to_dict_from_dict_msgpack_round_trip():
    m = ScaleModel([20.0, 15.0], config=ScaleConfig(length_scale=0.05, margin=1.5))
    xi, ph = cluster(0.3)
    m.update(xi, phase=ph)
    m.update(*cluster(0.7, xi=(-3000.0, 40.0)))
    blob = msgpack.packb(m.to_dict())
    r = ScaleModel.from_dict(msgpack.unpackb(blob))
    assert r.config == m.config and r.n_updates == 2 and r.n_points == m.n_points
    np.testing.assert_array_equal(r.default, m.default)
    np.testing.assert_allclose(r.table(GRID), m.table(GRID), rtol=1e-12)
    # an untrained model round-trips too
    e = ScaleModel.from_dict(msgpack.unpackb(msgpack.packb(ScaleModel(15.0, dim=2).to_dict())))
    np.testing.assert_array_equal(e.table(GRID), 15.0)


def test_from_dict_rejects_inconsistent_data():
    m = ScaleModel(15.0, dim=2)
    m.update(*cluster())
    d = m.to_dict()
    d["y"] = d["y"][:-1]
    with pytest.raises(ValueError):
        ScaleModel.from_dict(d)
    d = m.to_dict()
    d["x"][0] = [float("nan")]
    with pytest.raises(ValueError):
        ScaleModel.from_dict(d)


# ------------------------------------------------------------------------------------ thinning
def test_thinning_keeps_at_most_max_points():
    cfg = ScaleConfig(max_points=20)
    m = ScaleModel(15.0, dim=2, config=cfg)
    rng = np.random.default_rng(0)
    for _ in range(5):
        ph = rng.uniform(0, 1, 60)
        m.update(rng.uniform(50, 500, (60, 2)), phase=ph)
        assert m.n_points <= 20
    table = m.table(GRID)
    assert np.all(np.isfinite(table)) and np.all(table > 0)


def test_thinning_averages_within_a_bin():
    """Points closer than half a length scale collapse to their mean: the fit barely changes."""
    cfg = ScaleConfig(max_points=5)
    m = ScaleModel(15.0, dim=2, config=cfg)
    ph = np.full(40, 0.5) + np.linspace(0, 0.001, 40)
    m.update(np.tile([400.0, 400.0], (40, 1)), phase=ph)
    assert m.n_points == 1
    one = ScaleModel(15.0, dim=2, config=cfg)
    one.update(np.array([[400.0, 400.0]]), phase=np.array([ph.mean()]))
    np.testing.assert_allclose(m.table(GRID), one.table(GRID), rtol=1e-9)


def test_thinning_keeps_the_newest_intervention():
    """_thin keeps the newest bins: it used to keep the bins with the largest input (np.unique sorts the keys),
    so with position input a new intervention at small x was dropped entirely and L there stayed L0."""
    cfg = ScaleConfig(input="position", max_points=20)
    m = ScaleModel(15.0, dim=2, config=cfg)
    rng = np.random.default_rng(0)
    old = np.c_[rng.uniform(0.7, 0.9, 30), rng.uniform(0.1, 0.9, 30)]
    m.update(np.full((30, 2), 200.0), position=old)
    new = np.c_[rng.uniform(0.1, 0.3, 30), rng.uniform(0.1, 0.9, 30)]
    m.update(np.full((30, 2), 300.0), position=new)
    assert m.n_points <= 20
    kept = m._x
    assert np.all(kept[:, 0] < 0.5), f"older data kept over the newest intervention: x = {kept[:, 0]}"
    L_kept = m(position=kept)
    assert np.all(L_kept > 15.0 * 2), f"the newest intervention was thinned away: L there = {L_kept.min(axis=0)}"


# ------------------------------------------------------------------------------------ position input
def test_position_input_mode():
    cfg = ScaleConfig(input="position", length_scale=0.05)
    m = ScaleModel(15.0, dim=2, config=cfg)
    assert m.in_dim == 2
    np.testing.assert_array_equal(m(position=np.array([0.5, 0.5])), [15.0, 15.0])
    pos = np.c_[np.linspace(0.55, 0.75, 25), np.full(25, 0.6)]
    xi = np.tile([80.0, 900.0], (25, 1))
    m.update(xi, position=pos)
    L = m(position=np.array([0.65, 0.6]))
    assert L.shape == (2,)
    np.testing.assert_allclose(L, [100.0, 1125.0], rtol=0.05)
    many = m(position=pos)
    assert many.shape == (25, 2)
    np.testing.assert_allclose(m(position=np.array([0.1, 0.1])), [15.0, 15.0], rtol=1e-6)
    with pytest.raises(ValueError):
        m.table(GRID)  # a phase table needs phase input
    with pytest.raises(ValueError):
        m(phase=0.5)  # position model without a position
    r = ScaleModel.from_dict(msgpack.unpackb(msgpack.packb(m.to_dict())))
    np.testing.assert_allclose(r(position=pos), many, rtol=1e-12)


# ------------------------------------------------------------------------------------ validation
@pytest.mark.parametrize("default", [0.0, -1.0, float("nan"), float("inf"), [[1.0, 2.0]]])
def test_bad_default(default):
    with pytest.raises(ValueError):
        ScaleModel(default, dim=2)


@pytest.mark.parametrize(
    "kw",
    [
        dict(input="time"),
        dict(length_scale=0.0),
        dict(signal_var=-1.0),
        dict(noise_var=float("nan")),
        dict(margin=0.0),
        dict(min_scale=float("inf")),
    ],
)
def test_bad_config(kw):
    with pytest.raises(ValueError):
        ScaleConfig(**kw)


def test_bad_update_inputs():
    m = ScaleModel(15.0, dim=2)
    xi, ph = cluster(k=5)
    with pytest.raises(ValueError):
        m.update(np.array([[np.nan, 1.0]]), phase=np.array([0.5]))
    with pytest.raises(ValueError):
        m.update(xi, phase=np.r_[ph[:-1], np.nan])
    with pytest.raises(ValueError):
        m.update(xi, phase=ph[:3])  # length mismatch
    with pytest.raises(ValueError):
        m.update(np.ones((3, 3)), phase=np.zeros(4))  # 9 values as (k, 2) is not possible
    with pytest.raises(ValueError):
        m(phase=np.nan)
    assert m.n_points == 0 and m.n_updates == 0
    pm = ScaleModel(15.0, dim=2, config=ScaleConfig(input="position"))
    with pytest.raises(ValueError):
        pm.update(xi, phase=ph)  # needs positions
    with pytest.raises(ValueError):
        pm(position=np.array([np.inf, 0.5]))
