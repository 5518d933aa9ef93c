"""GMM + GMR reference distribution (math.md §2)."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.kmp.gmr import fit_gmm, gmr, reference_distribution, time_inputs


def _two_component_model():
    """Hand-built joint (s, x, y) mixture with correlated input/output blocks."""
    weights = np.array([0.3, 0.7])
    means = np.array([[0.2, 1.0, -1.0], [0.7, -0.5, 2.0]])
    covariances = np.array(
        [
            [[0.04, 0.02, -0.01], [0.02, 0.09, 0.01], [-0.01, 0.01, 0.05]],
            [[0.09, -0.03, 0.06], [-0.03, 0.16, -0.02], [0.06, -0.02, 0.25]],
        ]
    )
    for c in covariances:
        assert np.linalg.eigvalsh(c).min() > 0
    return weights, means, covariances


def _hand_gmr(weights, means, covariances, s):
    """Scalar-input GMR written out term by term (no vectorisation shared with the implementation)."""
    pdf = []
    m_c, s_c = [], []
    for p, m, S in zip(weights, means, covariances):
        var = S[0, 0]
        pdf.append(p * np.exp(-0.5 * (s - m[0]) ** 2 / var) / np.sqrt(2 * np.pi * var))
        gain = S[1:, 0] / var  # Sigma_es Sigma_ss^-1, (2,)
        m_c.append(m[1:] + gain * (s - m[0]))
        s_c.append(S[1:, 1:] - np.outer(S[1:, 0], S[0, 1:]) / var)
    h = np.array(pdf) / np.sum(pdf)
    mean = sum(h[c] * m_c[c] for c in range(2))
    cov = sum(h[c] * (s_c[c] + np.outer(m_c[c] - mean, m_c[c] - mean)) for c in range(2))
    return mean, cov, h


@pytest.mark.parametrize("s", [-0.3, 0.0, 0.2, 0.45, 0.7, 1.1])
def test_gmr_two_components_by_hand(s):
    w, m, c = _two_component_model()
    mean_ref, cov_ref, h = _hand_gmr(w, m, c, s)
    mu, sigma = gmr(w, m, c, np.array([[s]]), n_inputs=1)
    assert mu.shape == (1, 2) and sigma.shape == (1, 2, 2)
    np.testing.assert_allclose(mu[0], mean_ref, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(sigma[0], cov_ref, rtol=1e-11, atol=1e-13)
    # The test point set covers both regimes: each component dominates somewhere, and mixes in between.
    assert 0 <= h[0] <= 1


def test_gmr_hand_case_is_a_real_mixture():
    """Sanity of the hand case itself: the moment-matched covariance exceeds the average conditional
    covariance where the components disagree (the between-component spread term matters)."""
    w, m, c = _two_component_model()
    _, cov, h = _hand_gmr(w, m, c, 0.45)
    assert 0.05 < h[0] < 0.95
    mu, sigma = gmr(w, m, c, np.array([[0.45]]), n_inputs=1)
    avg_cond = sum(
        h[k] * (c[k][1:, 1:] - np.outer(c[k][1:, 0], c[k][0, 1:]) / c[k][0, 0]) for k in range(2)
    )
    assert np.linalg.eigvalsh(sigma[0] - avg_cond).max() > 0.1


def test_gmr_vectorised_queries_match_single():
    w, m, c = _two_component_model()
    q = np.linspace(-0.2, 1.2, 15)[:, None]
    mu, sigma = gmr(w, m, c, q, n_inputs=1)
    for k, s in enumerate(q[:, 0]):
        mean_ref, cov_ref, _ = _hand_gmr(w, m, c, s)
        np.testing.assert_allclose(mu[k], mean_ref, rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(sigma[k], cov_ref, rtol=1e-11, atol=1e-13)


def test_gmr_single_component_is_gaussian_conditioning():
    w, m, c = _two_component_model()
    mu, sigma = gmr(w[:1] / w[0], m[:1], c[:1], np.array([[0.1], [0.9]]), n_inputs=1)
    S = c[0]
    for k, s in enumerate([0.1, 0.9]):
        np.testing.assert_allclose(mu[k], m[0, 1:] + S[1:, 0] / S[0, 0] * (s - m[0, 0]), rtol=1e-13)
        np.testing.assert_allclose(sigma[k], S[1:, 1:] - np.outer(S[1:, 0], S[0, 1:]) / S[0, 0], rtol=1e-12)


def test_gmr_far_query_does_not_overflow():
    """Responsibilities are computed in log space: a query far from every component still gives the
    nearest component's conditional, not NaN."""
    w, m, c = _two_component_model()
    mu, sigma = gmr(w, m, c, np.array([[40.0]]), n_inputs=1)
    assert np.all(np.isfinite(mu)) and np.all(np.isfinite(sigma))


def test_gmr_bad_query_columns():
    w, m, c = _two_component_model()
    with pytest.raises(ValueError):
        gmr(w, m, c, np.zeros((3, 2)), n_inputs=1)


# ------------------------------------------------------------------ reference_distribution on demos
def _synthetic_demos(m=6, n=60, noise=0.03, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n)
    base = np.c_[np.sin(2 * np.pi * t), t**2 - 0.5]
    demos = np.empty((m, n, 2))
    for k in range(m):
        # per-demo smooth offset plus small noise: spread grows in the middle of the motion
        off = rng.normal(scale=0.1, size=2) * np.sin(np.pi * t)[:, None]
        demos[k] = base + off + rng.normal(scale=noise, size=(n, 2))
    return demos


def test_reference_distribution_shapes_and_pd():
    demos = _synthetic_demos()
    rd = reference_distribution(demos, n_points=50, n_components=6)
    assert rd.s.shape == (50, 1)
    assert rd.mu.shape == (50, 2)
    assert rd.sigma.shape == (50, 2, 2)
    np.testing.assert_allclose(rd.s[:, 0], np.linspace(0, 1, 50))
    np.testing.assert_array_equal(rd.sigma, np.swapaxes(rd.sigma, 1, 2))
    assert np.linalg.eigvalsh(rd.sigma).min() > 0


def test_reference_distribution_default_grid_is_demo_length():
    demos = _synthetic_demos(n=40)
    rd = reference_distribution(demos, n_components=4)
    assert rd.s.shape == (40, 1) and rd.mu.shape == (40, 2) and rd.sigma.shape == (40, 2, 2)


def test_reference_distribution_tracks_demo_average():
    demos = _synthetic_demos()
    rd = reference_distribution(demos, n_components=8)  # grid = the demos' own time grid
    avg = demos.mean(axis=0)
    err = np.abs(rd.mu - avg)
    assert err.max() < 0.08, err.max()
    assert err.mean() < 0.025, err.mean()
    # and the spread is of the order of the demos' spread (not zero, not huge)
    demo_var = demos.var(axis=0).mean()
    gmr_var = np.trace(rd.sigma, axis1=1, axis2=2).mean() / 2
    assert 0.2 * demo_var < gmr_var < 5 * demo_var


def test_reference_distribution_jitter():
    demos = _synthetic_demos()
    a = reference_distribution(demos, n_points=30, n_components=4, jitter=0.0)
    b = reference_distribution(demos, n_points=30, n_components=4, jitter=1e-3)
    np.testing.assert_allclose(b.sigma - a.sigma, np.broadcast_to(1e-3 * np.eye(2), a.sigma.shape), atol=1e-12)


def test_reference_distribution_deterministic_with_seed():
    demos = _synthetic_demos()
    a = reference_distribution(demos, n_points=20, n_components=5, seed=3)
    b = reference_distribution(demos, n_points=20, n_components=5, seed=3)
    np.testing.assert_array_equal(a.mu, b.mu)
    np.testing.assert_array_equal(a.sigma, b.sigma)


def test_fit_gmm_matches_gmr_on_its_own_parameters():
    demos = _synthetic_demos()
    gmm = fit_gmm(demos, n_components=5, seed=0)
    s = time_inputs(25)
    mu, sigma = gmr(gmm.weights_, gmm.means_, gmm.covariances_, s, n_inputs=1)
    rd = reference_distribution(demos, n_points=25, n_components=5, seed=0, jitter=0.0)
    np.testing.assert_allclose(rd.mu, mu, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(rd.sigma, sigma, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((10, 2)),  # one demo without the M axis: wrong ndim
        np.zeros((2, 10, 2, 1)),  # too many axes
        np.zeros((2, 1, 2)),  # one point per demo
    ],
)
def test_bad_demo_shapes(bad):
    with pytest.raises(ValueError):
        reference_distribution(bad)


def test_ragged_demos_rejected():
    ragged = [np.zeros((10, 2)), np.zeros((12, 2))]
    with pytest.raises(ValueError):
        reference_distribution(ragged)


def test_nan_demos_rejected():
    demos = _synthetic_demos()
    demos[2, 5, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        reference_distribution(demos)
    demos[2, 5, 1] = np.inf
    with pytest.raises(ValueError):
        fit_gmm(demos)


def test_too_many_components_rejected():
    demos = _synthetic_demos(m=1, n=5)
    with pytest.raises(ValueError):
        fit_gmm(demos, n_components=6)
