"""Via-point adaptation of the LC-NS-KMP (khgrl.common.kmp.adapt): the adapted model equals an independent solution
of the same problem -- the via-points put into the reference database, paper eq. (2) solved in weight space by cvxpy
-- and keeps its hard constraints, its projector bound and its per-step tables."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.kmp.adapt import adapt_model, snap_via_points
from khgrl.common.kmp.lcnskmp import LCNSKMP
from khgrl.common.tasks.scene import ViaPoint

from kmp_problems import BETA, BOX_C, BOX_G, LAM, Reference, make_reference
from test_kmp import FeatureKernel, primal_eta

VIA = [ViaPoint(0.30, (0.55, -0.30), 1e4), ViaPoint(0.71, (-0.2, 0.1), 1e5), ViaPoint(1.0, (0.1, 0.45), 1e4)]


@pytest.fixture(scope="module")
def setup():
    ref = make_reference(50, seed=1)
    feat = FeatureKernel()
    s_star = np.r_[ref.s, np.linspace(-0.05, 1.05, 31)[:, None]]
    return ref, feat, s_star


def _database(ref: Reference, via) -> Reference:
    """The reference database with each via-point replacing the reference point at its (nearest) input, written
    out independently of khgrl.common.kmp.adapt."""
    mu, sigma = ref.mu.copy(), ref.sigma.copy()
    for v in via:
        n = int(round(v.phase * (ref.n - 1)))
        mu[n] = v.position
        sigma[n] = np.eye(ref.o) / v.precision
    return Reference(s=ref.s, mu=mu, sigma=sigma)


@pytest.mark.parametrize("constrained", [False, True])
def test_adapted_equals_independent_solution(setup, constrained):
    """Adapted LC-NS-KMP = eq. (2) on the database with the via-points, to 1e-6, on and off the grid, with and
    without an action xi, with and without the hard constraints (which the via-point at phase 0.3 violates)."""
    ref, feat, s_star = setup
    cons = dict(G=BOX_G, c=BOX_C) if constrained else {}
    base = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=feat,
                   constraints=(BOX_G, BOX_C) if constrained else None)
    adapted = adapt_model(base, VIA)
    db = _database(ref, VIA)
    for xi, s_hat in [(None, None), (np.array([6.0, -4.0]), np.array([0.42]))]:
        got = adapted.predict(s_star, xi, s_hat)
        want = primal_eta(feat, db, s_star, xi=xi, s_hat=s_hat, **cons)
        assert np.abs(got - want).max() <= 1e-6
    n, xi = 20, np.array([30.0, -20.0])  # the per-step tables of the adapted model
    want = primal_eta(feat, db, ref.s[n:n + 1], xi=xi, s_hat=ref.s[n], **cons)[0]
    assert np.abs(adapted.grid_step(n, xi) - want).max() <= 1e-6


def test_mean_passes_through_via_points_and_band_narrows(setup):
    ref, feat, _ = setup
    base = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=feat)
    adapted = adapt_model(base, VIA)
    for v in VIA:
        n = int(round(v.phase * (ref.n - 1)))
        assert np.abs(adapted.grid_mean[n] - v.position).max() < 0.02
        assert np.abs(base.grid_mean[n] - v.position).max() > 0.1  # it really moved
        # the projector is bounded by beta Sigma_bar there (math.md §4): the band shrinks at the via-point
        assert np.linalg.eigvalsh(BETA / v.precision * np.eye(2) - adapted.grid_projector[n]).min() >= -1e-12
    assert np.array_equal(base.grid_mean, LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA,
                                                  kernel=feat).grid_mean)  # the base model is untouched


def test_constraints_hold_with_a_via_point_outside_them(setup):
    ref, feat, _ = setup
    base = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=feat, constraints=(BOX_G, BOX_C))
    adapted = adapt_model(base, [ViaPoint(0.5, (0.0, 2.0), 1e6)])  # far above the box's y <= 0.35
    assert adapted.constraints is not None
    for n in range(ref.n):
        p = adapted.grid_step(n, np.array([5.0, 5.0]))
        assert np.all(BOX_G @ p >= BOX_C - 1e-8)


def test_snapping_and_bad_via_points(setup):
    ref, feat, _ = setup
    base = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=feat)
    assert [s.step for s in snap_via_points(base, [ViaPoint(0.301, (0, 0)), ViaPoint(0.0, (0, 0))])] == [15, 0]
    assert adapt_model(base, []) is base
    for bad, words in [(ViaPoint(1.2, (0, 0)), "phase"), (ViaPoint(0.5, (0, 0, 0)), "position"),
                       (ViaPoint(0.5, (0, np.nan)), "position"), (ViaPoint(0.5, (0, 0), 0.0), "precision")]:
        with pytest.raises(ValueError, match=words):
            adapt_model(base, [bad])
    with pytest.raises(ValueError, match="like an earlier via-point"):
        adapt_model(base, [ViaPoint(0.49, (0, 0)), ViaPoint(0.495, (1, 1))])
