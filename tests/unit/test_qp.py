"""The dual constraint QP  min_{a >= 0} 1/2 a^T Q a + q^T a  (math.md §3) against cvxpy.

With Q = H H^T the problem is the dual of the least-distance problem min 1/2 ||z||^2 s.t. H z >= -q,
whose solution z* = H^T a* is unique even when a* is not (Q singular): we compare z (equivalently Q a)
and the objective value, never a itself.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
from khgrl.common.kmp.qp import QPError, lcp_residual, solve_dual_qp, solve_least_distance_interior


def _random_problem(m: int, r: int, seed: int, scale: float = 1.0):
    """Q = H H^T (rank min(m, r)) and q such that the least-distance primal has an interior point z0
    (slack >= 0.05 on every row, so small perturbations of q stay feasible) but z = 0 is infeasible
    (some q_i < 0), so constraints are active."""
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(m, r)) * scale
    z0 = rng.normal(size=r) * 2.0
    if np.max(H @ z0) < 1.0:  # make sure some rows are violated at z = 0
        z0 *= -1.0
    u = 0.05 + rng.exponential(size=m) * 0.5
    q = -H @ z0 + u
    assert np.any(q < 0)
    return H, H @ H.T, q


def _cvxpy_least_distance(H: np.ndarray, q: np.ndarray) -> np.ndarray:
    z = cp.Variable(H.shape[1])
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(z)), [H @ z >= -q])
    prob.solve(solver="CLARABEL", tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, tol_ktratio=1e-9)
    assert prob.status == "optimal"
    return z.value


def _objective(Q, q, a):
    return 0.5 * a @ Q @ a + q @ a


# (m, r): full rank (m <= r) and rank-deficient (m > r) problems
SIZES = [(5, 5), (8, 12), (12, 4), (30, 6), (40, 3), (60, 20)]


@pytest.mark.parametrize("m,r", SIZES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_solve_dual_qp_matches_cvxpy(m, r, seed):
    H, Q, q = _random_problem(m, r, seed)
    a, active = solve_dual_qp(Q, q)
    z_ref = _cvxpy_least_distance(H, q)
    scale = max(1.0, np.abs(q).max())
    assert np.all(a >= 0)
    np.testing.assert_allclose(H.T @ a, z_ref, atol=1e-7 * scale)
    # dual objective = -1/2 ||z*||^2 (strong duality)
    assert _objective(Q, q, a) == pytest.approx(-0.5 * z_ref @ z_ref, rel=1e-8, abs=1e-9)
    assert lcp_residual(Q, q, a) < 1e-9 * scale
    # the returned active set is exactly the support of a, and those rows are tight
    assert set(active) >= set(np.flatnonzero(a > 0))
    np.testing.assert_allclose((Q @ a + q)[active], 0.0, atol=1e-9 * scale)


@pytest.mark.parametrize("seed", range(4))
def test_rank_deficient_q_many_dependent_rows(seed):
    """m = 50 constraints in r = 2 dimensions: Q has rank 2, almost every row is a dependent normal."""
    H, Q, q = _random_problem(50, 2, seed)
    assert np.linalg.matrix_rank(Q) == 2
    a, active = solve_dual_qp(Q, q)
    z_ref = _cvxpy_least_distance(H, q)
    np.testing.assert_allclose(H.T @ a, z_ref, atol=1e-7 * max(1.0, np.abs(q).max()))
    assert len(active) <= 2
    assert lcp_residual(Q, q, a) < 1e-9 * max(1.0, np.abs(q).max())


def test_feasible_start_returns_zero():
    """q >= 0: a = 0 is optimal (the KKT shortcut) and nothing is active."""
    H, Q, _ = _random_problem(10, 4, 0)
    q = np.abs(np.random.default_rng(0).normal(size=10))
    a, active = solve_dual_qp(Q, q)
    np.testing.assert_array_equal(a, 0.0)
    assert active == []


@pytest.mark.parametrize("m,r", [(12, 4), (30, 6), (40, 40)])
def test_warm_start_equals_cold_start(m, r):
    H, Q, q = _random_problem(m, r, 7)
    a_cold, act_cold = solve_dual_qp(Q, q)
    rng = np.random.default_rng(3)
    guesses = [
        list(act_cold),  # the exact active set
        list(reversed(act_cold)),
        list(act_cold[:1]),  # a subset
        sorted(set(act_cold) | set(rng.choice(m, size=3, replace=False).tolist())),  # a superset, some wrong
        rng.choice(m, size=min(m, r + 3), replace=False).tolist(),  # random, possibly dependent rows
        list(range(m)),  # everything (singular Gram block when m > r)
    ]
    for guess in guesses:
        a_warm, _ = solve_dual_qp(Q, q, guess)
        np.testing.assert_allclose(Q @ a_warm, Q @ a_cold, atol=1e-8 * max(1.0, np.abs(q).max()))
        assert _objective(Q, q, a_warm) == pytest.approx(_objective(Q, q, a_cold), rel=1e-10, abs=1e-10)
        assert lcp_residual(Q, q, a_warm) < 1e-9 * max(1.0, np.abs(q).max())


def test_warm_start_on_perturbed_problem():
    """The intended use: the previous step's active set warm-starts a slightly different q."""
    H, Q, q = _random_problem(30, 6, 11)
    _, act = solve_dual_qp(Q, q)
    q2 = q + 0.05 * np.random.default_rng(0).normal(size=q.shape)
    a_warm, _ = solve_dual_qp(Q, q2, act)
    a_cold, _ = solve_dual_qp(Q, q2)
    np.testing.assert_allclose(H.T @ a_warm, H.T @ a_cold, atol=1e-9)
    np.testing.assert_allclose(H.T @ a_warm, _cvxpy_least_distance(H, q2), atol=1e-7)


def test_lcp_residual_detects_violations():
    Q = np.array([[2.0, 0.0], [0.0, 1.0]])
    q = np.array([-2.0, 1.0])
    assert lcp_residual(Q, q, np.array([1.0, 0.0])) == 0.0  # the solution
    assert lcp_residual(Q, q, np.array([0.0, 0.0])) == pytest.approx(2.0)  # slack w_0 = -2
    assert lcp_residual(Q, q, np.array([-0.5, 0.0])) == pytest.approx(3.0)  # w_0 = -3, a_0 < 0
    assert lcp_residual(Q, q, np.array([1.0, 0.5])) == pytest.approx(0.75)  # a_1 * w_1 = 0.5 * 1.5


def test_incompatible_constraints_raise():
    # z >= 1 and -z >= 1 (H = [1, -1]^T, q = [-1, -1]): the dual is unbounded along a = t (1, 1).
    Q = np.array([[1.0, -1.0], [-1.0, 1.0]])
    q = np.array([-1.0, -1.0])
    with pytest.raises(QPError):
        solve_dual_qp(Q, q)


def test_incompatible_constraints_raise_higher_dim():
    rng = np.random.default_rng(5)
    H = rng.normal(size=(6, 3))
    h = rng.normal(size=3)
    H[2], H[4] = h, -2.0 * h  # h.z >= 1 and -2 h.z >= 2  <=>  h.z <= -1
    z0 = rng.normal(size=3)
    q = -H @ z0 + 0.1
    q[2], q[4] = -1.0, -2.0
    with pytest.raises(QPError):
        solve_dual_qp(H @ H.T, q)


def test_least_distance_interior_fallback_matches_cvxpy():
    H, Q, q = _random_problem(20, 5, 4)
    z, a_ip = solve_least_distance_interior(H, -q)
    np.testing.assert_allclose(z, _cvxpy_least_distance(H, q), atol=1e-6)
    a, _ = solve_dual_qp(Q, q)
    np.testing.assert_allclose(z, H.T @ a, atol=1e-6)
    np.testing.assert_allclose(z, H.T @ a_ip, atol=1e-5)  # its multipliers reproduce z = H^T a (dual accuracy ~2e-6)
    assert np.all(a_ip >= 0)


def test_least_distance_interior_infeasible_raises():
    H = np.array([[1.0], [-1.0]])
    with pytest.raises(QPError):
        solve_least_distance_interior(H, np.array([1.0, 1.0]))


def test_kmp_dual_matches_cvxpy(box_model):
    """The model's own (numerically singular, cond >> 1e12) Q and q from the box-constrained model."""
    Q, q = box_model._Q, box_model._q0
    assert np.any(q < 0)
    a, _ = solve_dual_qp(Q, q)
    evals, evecs = np.linalg.eigh(box_model._M)
    keep = evals > 1e-12 * evals[-1]
    R = evecs[:, keep] * np.sqrt(evals[keep])
    n, o, f = box_model.n_points, box_model.out_dim, box_model.n_constraints
    H = np.einsum("nfo,nor->nfr", box_model._G, R.reshape(n, o, -1)).reshape(n * f, -1)
    z_ref = _cvxpy_least_distance(H, q)
    np.testing.assert_allclose(H.T @ a, z_ref, atol=1e-7)
    assert lcp_residual(Q, q, a) < 1e-9
