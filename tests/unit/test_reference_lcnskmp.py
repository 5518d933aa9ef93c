"""Equivalence with the authors' library ``lc-ns-kmp`` 0.1.0 (C++/PIQP, import name ``lc_ns_kmp``).

Its conventions (math.md §6): kernel k = exp(-l ||d||^2) -> ``RBF.from_precision(l)``;
A = (K + gamma Sigma)^-1 in ``predict_LCNS``; K_low = I (it never divides by k(s_hat, s_hat), which is 1
for its kernel anyway).

Array layouts, found by experiment with the installed wheel (and consistent with its pybind11 bindings):

* ``LC_NS_KMP(output_dim, horizon, lambda_, beta, l)``; ``horizon`` must equal the number of reference
  points N (a mismatch segfaults: N is used as a loop bound over the reference arrays).
* ``s``, ``s_star``: (N, I) / (Q, I), one input per ROW. (1, N) segfaults.
* ``mu``: (N, O), one mean per row. (O, N) segfaults.
* ``sigma``: stacked (N, O, O). The block-diagonal (N*O, N*O) matrix is rejected with
  ``ValueError: Sigma stack must have shape (N, d, d)``.
* ``xi``: (O,) or (O, 1); (1, O) raises TypeError. ``s_hat``: (I,) (e.g. ``s[n]``); a bare float raises
  TypeError.
* ``add_constraints(g, c)``: g (F, O), one normal per row; c (F,) or (F, 1). The docstring says
  "g^T eta + c <= 0", but the QP enforces **g^T eta >= c** (``test_constraint_sign_convention``).
  ``predict_LCNS`` segfaults when no constraint was added, so an inactive one is added instead.
* Output: (Q, O). ``predict`` (plain lambda-KMP, A = (K + lambda Sigma)^-1) and ``predict_LC`` (LC-KMP,
  beta = 0) loop over N rows of ``s_star``, not Q: pass ``s_star`` with N rows there.

Agreement measured (N = 40, O = 2): inactive constraints ~3e-13; active box constraints up to ~2.2e-6
-- PIQP's default tolerance: against an independent cvxpy solution of the same dual, ours is within
1e-10 and lc_ns_kmp within 2.2e-6.
"""

from __future__ import annotations

import numpy as np
import pytest

lc_ns_kmp = pytest.importorskip("lc_ns_kmp")

from khgrl.common.kmp.kernels import RBF  # noqa: E402
from khgrl.common.kmp.lcnskmp import LCNSKMP  # noqa: E402

from kmp_problems import BETA, BOX_C, BOX_G, LAM, LOOSE_C, PRECISION  # noqa: E402

INACTIVE_G = np.array([[1.0, 0.0]])
INACTIVE_C = np.array([-100.0])  # x >= -100 (or x <= 100 under the documented sign): never active


def _theirs(ref, G, c, xi, s_hat, s_star, lam=LAM, beta=BETA):
    kmp = lc_ns_kmp.LC_NS_KMP(ref.o, ref.n, lam, beta, PRECISION)
    kmp.add_constraints(G, c)
    return kmp.predict_LCNS(s_star, xi, s_hat, ref.s, ref.mu, ref.sigma)


def _ours(ref, G=None, c=None, lam=LAM, beta=BETA):
    cons = None if G is None else (G, c)
    return LCNSKMP(ref.s, ref.mu, ref.sigma, lam=lam, beta=beta, kernel=RBF.from_precision(PRECISION), constraints=cons)


@pytest.fixture(scope="module")
def queries(ref):
    return np.r_[ref.s, np.linspace(0.003, 0.997, 21)[:, None]]


CASES = [
    (np.zeros(2), 0),
    (np.array([30.0, -20.0]), 12),
    (np.array([-50.0, 40.0]), 0.537),  # off-grid s_hat
    (np.array([5.0, 5.0]), 39),
]


def _s_hat(ref, where):
    return ref.s[where] if isinstance(where, int) else np.array([where])


@pytest.mark.parametrize("xi,where", CASES)
def test_unconstrained_equivalent(ref, queries, xi, where):
    """One inactive constraint on their side, none on ours: same model."""
    s_hat = _s_hat(ref, where)
    theirs = _theirs(ref, INACTIVE_G, INACTIVE_C, xi, s_hat, queries)
    ours = _ours(ref).predict(queries, xi, s_hat)
    assert theirs.shape == ours.shape == (queries.shape[0], 2)
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-10)


@pytest.mark.parametrize("xi,where", CASES)
def test_inactive_box_equivalent(ref, queries, xi, where):
    s_hat = _s_hat(ref, where)
    theirs = _theirs(ref, BOX_G, LOOSE_C, xi, s_hat, queries)
    ours = _ours(ref, BOX_G, LOOSE_C).predict(queries, xi, s_hat)
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-10)


@pytest.mark.parametrize("xi,where", CASES)
def test_active_box_equivalent(ref, queries, xi, where):
    """Active constraints: agreement is limited by PIQP's accuracy (measured <= 2.2e-6)."""
    s_hat = _s_hat(ref, where)
    theirs = _theirs(ref, BOX_G, BOX_C, xi, s_hat, queries)
    ours = _ours(ref, BOX_G, BOX_C).predict(queries, xi, s_hat)
    free = _ours(ref).predict(ref.s, xi, s_hat)
    assert (free @ BOX_G.T - BOX_C).min() < -0.05  # the box really cuts the trajectory
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-5)
    # both are feasible on the grid
    assert (theirs[: ref.n] @ BOX_G.T - BOX_C).min() >= -1e-8
    assert (ours[: ref.n] @ BOX_G.T - BOX_C).min() >= -1e-8


def test_constraint_sign_convention(ref):
    """g = [1, 0], c = 0.5: the library enforces g^T eta >= c (x >= 0.5), not its documented
    g^T eta + c <= 0 (which would be x <= -0.5)."""
    g, c = np.array([[1.0, 0.0]]), np.array([0.5])
    theirs = _theirs(ref, g, c, np.zeros(2), ref.s[0], ref.s)
    assert theirs[:, 0].min() >= 0.5 - 1e-8
    assert theirs[:, 0].max() > 0.5  # so x <= -0.5 is certainly not what is enforced
    ours = _ours(ref, g, c).predict(ref.s)
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-5)
    # c given as (F, 1) is the same
    kmp = lc_ns_kmp.LC_NS_KMP(2, ref.n, LAM, BETA, PRECISION)
    kmp.add_constraints(g, c[:, None])
    np.testing.assert_array_equal(kmp.predict_LCNS(ref.s, np.zeros(2), ref.s[0], ref.s, ref.mu, ref.sigma), theirs)


def test_layouts(ref):
    """The accepted/rejected layouts listed in the module docstring (the non-crashing ones)."""
    xi = np.array([3.0, -2.0])
    base = _theirs(ref, INACTIVE_G, INACTIVE_C, xi, ref.s[7], ref.s)
    assert base.shape == (ref.n, 2)
    # xi as a column (O, 1): same result
    np.testing.assert_array_equal(_theirs(ref, INACTIVE_G, INACTIVE_C, xi[:, None], ref.s[7], ref.s), base)
    # a subset of query rows (Q, I)
    np.testing.assert_array_equal(_theirs(ref, INACTIVE_G, INACTIVE_C, xi, ref.s[7], ref.s[:5]), base[:5])
    kmp = lc_ns_kmp.LC_NS_KMP(2, ref.n, LAM, BETA, PRECISION)
    kmp.add_constraints(INACTIVE_G, INACTIVE_C)
    import scipy.linalg

    with pytest.raises(ValueError, match="Sigma stack"):
        kmp.predict_LCNS(ref.s, xi, ref.s[7], ref.s, ref.mu, scipy.linalg.block_diag(*ref.sigma))
    with pytest.raises(TypeError):
        kmp.predict_LCNS(ref.s, xi[None, :], ref.s[7], ref.s, ref.mu, ref.sigma)


def test_their_predict_is_lambda_kmp(ref):
    """Their ``predict`` is the plain KMP mean k* (K + lambda Sigma)^-1 mu: ours with lam + beta = lambda."""
    lam_theirs = 1.5
    kmp = lc_ns_kmp.LC_NS_KMP(2, ref.n, lam_theirs, BETA, PRECISION)
    theirs = kmp.predict(ref.s, ref.s, ref.mu, ref.sigma)
    ours = _ours(ref, lam=lam_theirs / 2, beta=lam_theirs / 2).predict(ref.s)
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-10)


def test_their_predict_lc_is_beta_zero_limit(ref):
    """``predict_LC`` (LC-KMP, A = (K + lambda Sigma)^-1, no null space): ours with beta -> 0."""
    lam_theirs = 1.5
    kmp = lc_ns_kmp.LC_NS_KMP(2, ref.n, lam_theirs, BETA, PRECISION)
    kmp.add_constraints(BOX_G, BOX_C)
    theirs = kmp.predict_LC(ref.s, ref.s, ref.mu, ref.sigma)
    ours = _ours(ref, BOX_G, BOX_C, lam=lam_theirs - 1e-12, beta=1e-12).predict(ref.s)
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-5)
