"""The LC-NS-KMP constraint QP (the dual of eq. 3): ``min_{a >= 0} 1/2 a^T Q a + q^T a``.

``Q = Gbar^T M Gbar`` with ``M = K A Sigma`` (math.md §3). With a smooth kernel M has a rapidly decaying
spectrum and constraint rows at neighbouring grid points are nearly collinear, so Q is numerically
singular (measured cond > 1e12 on a 40-row active block): block pivoting cycles and OSQP on this dual does
not reach 1e-6 in seconds. The problem is the dual of the *least-distance* problem

    min_z 1/2 ||z||^2   s.t.   H z >= -q,     Q = H H^T  (any factor H of Q),

for which Goldfarb & Idnani's dual active-set method (1983) is exact and finite. We run it in Gram form,
so only Q's entries are needed (never a factor H): the active set's Gram block is Cholesky-factored and
grown by one row per added constraint (the new diagonal is the squared length of the new constraint
normal orthogonal to the active ones -- a constraint with a numerically dependent normal is never added
by a full step). A per-step problem with a few active constraints costs a few O(m k) vector updates.

:func:`solve_least_distance_interior` solves the least-distance form with an interior-point method
(Clarabel through cvxpy), given an explicit factor H: the fallback for degenerate constraint sets.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["QPError", "solve_dual_qp", "solve_least_distance_interior", "lcp_residual"]


_trtrs = scipy.linalg.get_lapack_funcs("trtrs", dtype=np.float64)


def _tri_solve(L: np.ndarray, b: np.ndarray, trans: int = 0) -> np.ndarray:
    """Lower-triangular solve via LAPACK directly (scipy's wrapper costs ~40 µs per call here)."""
    x, info = _trtrs(L, b, lower=1, trans=trans)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular triangular factor (info={info})")
    return x


class QPError(RuntimeError):
    """The constraint QP has no solution (incompatible constraints) or did not converge."""


def lcp_residual(Q: np.ndarray, q: np.ndarray, a: np.ndarray) -> float:
    """Largest violation of a >= 0, w = Q a + q >= 0, and |a_i w_i| (complementarity)."""
    w = Q @ a + q
    return float(max(np.max(-a, initial=0.0), np.max(-w, initial=0.0), np.max(np.abs(a * w), initial=0.0)))


def _warm_state(Q: np.ndarray, q: np.ndarray, guess: list[int]) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Largest usable prefix of a guessed active set: a_A = -Q_AA^-1 q_A must be >= 0 (dual feasible with the
    guessed rows tight), which is a valid Goldfarb-Idnani state to continue from. Drops negative rows twice,
    then gives up (cold start)."""
    active = list(guess)
    for _ in range(3):
        if not active:
            break
        try:
            L = np.linalg.cholesky(Q[np.ix_(active, active)])
        except np.linalg.LinAlgError:
            break
        a_act = _tri_solve(L, _tri_solve(L, -q[active]), trans=1)
        if np.all(a_act >= 0.0):
            return active, L, a_act
        active = [i for i, v in zip(active, a_act) if v > 0.0]
    return [], np.zeros((0, 0)), np.zeros(0)


def solve_dual_qp(
    Q: np.ndarray,
    q: np.ndarray,
    active: list[int] | None = None,
    *,
    tol: float = 1e-12,
    dep_tol: float = 1e-9,
    dep_feas_tol: float = 1e-6,
    max_iter: int | None = None,
) -> tuple[np.ndarray, list[int]]:
    """Goldfarb-Idnani (identity Hessian, Gram form) for ``min_{a>=0} 1/2 a^T Q a + q^T a``.

    Args:
        Q: (m, m) symmetric PSD.
        q: (m,) linear term; ``w = Q a + q`` is the constraint slack.
        active: optional warm start (e.g. the previous control step's active rows).
        tol: slack tolerance, relative to ``max(1, max|q|)``.
        dep_tol: a normal whose component orthogonal to the active normals has squared length below
            ``dep_tol * Q_pp`` is treated as dependent (M's round-off floor is ~1e-9 relative).
        dep_feas_tol: a dependent row violated by less than this (relative to ``max(1, max|q|)``) is set
            aside instead of declaring the constraints incompatible (degenerate constraint sets).
        max_iter: iteration cap (default 4 m + 20).

    Returns:
        ``(a, active)``: a (m,) >= 0 with ``Q a + q >= -tol`` and complementarity, and the active rows.

    Raises:
        QPError: incompatible constraints, or the cap was hit.
    """
    m = q.shape[0]
    eps = tol * max(1.0, float(np.max(np.abs(q), initial=0.0)))
    max_iter = 4 * m + 20 if max_iter is None else max_iter
    a = np.zeros(m)
    slack = q.astype(np.float64, copy=True)
    active, L, a_act = _warm_state(Q, q, active or [])
    if active:
        a[active] = a_act
        slack += a_act @ Q[active]
        slack[active] = 0.0
    # A row whose normal is numerically dependent on the active ones cannot be exchanged into the active
    # set. When its violation is tiny it is set aside: this happens with degenerate constraint sets, e.g. an
    # equality written as two inequalities at every grid point, where ~40 neighbouring rows span only the
    # kernel's numerical rank; what remains is ~1e-7 (measured), so such rows hold to dep_feas_tol.
    dep_eps = max(eps, dep_feas_tol * max(1.0, float(np.max(np.abs(q), initial=0.0))))
    skipped = np.zeros(m, dtype=bool)
    it = 0
    while True:
        p = int(np.argmin(np.where(skipped, np.inf, slack)))
        if skipped[p] or slack[p] >= -eps:
            return a, active
        q_pp = float(Q[p, p])
        # Add p, dropping blocking constraints whose multiplier would turn negative.
        while True:
            it += 1
            if it > max_iter:
                raise QPError(f"dual QP did not converge in {max_iter} iterations")
            if active:
                l_vec = _tri_solve(L, Q[p, active])
                rvec = _tri_solve(L, l_vec, trans=1)
                dd = q_pp - float(l_vec @ l_vec)
                step_dir = Q[p] - rvec @ Q[active]  # slack change per unit of a_p (Q symmetric: rows)
            else:
                l_vec = rvec = np.zeros(0)
                dd = q_pp
                step_dir = Q[p]
            independent = dd > dep_tol * q_pp
            t1 = -slack[p] / dd if independent else np.inf
            t2, j = np.inf, -1
            if active:
                pos = rvec > 0.0
                if np.any(pos):
                    ratios = np.where(pos, a[active] / np.where(pos, rvec, 1.0), np.inf)
                    j = int(np.argmin(ratios))
                    t2 = float(ratios[j])
            if not (np.isfinite(t1) or np.isfinite(t2)):
                if slack[p] >= -dep_eps:
                    skipped[p] = True
                    break
                raise QPError(
                    f"constraints are incompatible: row {p} (violated by {-slack[p]:.3g}) cannot hold with the "
                    f"active rows {active}"
                )
            t = min(t1, t2)
            slack += t * step_dir
            if active:
                a[active] -= t * rvec
            a[p] += t
            if t1 <= t2:  # full step: p becomes active
                k = len(active)
                L_new = np.zeros((k + 1, k + 1))
                L_new[:k, :k] = L
                L_new[k, :k] = l_vec
                L_new[k, k] = np.sqrt(dd)
                L = L_new
                active.append(p)
                slack[p] = 0.0
                break
            # partial step: drop the blocking constraint and refactor the (smaller) active Gram block
            a[active[j]] = 0.0
            del active[j]
            L = np.linalg.cholesky(Q[np.ix_(active, active)]) if active else np.zeros((0, 0))
            if slack[p] >= -eps:
                break
        np.maximum(a, 0.0, out=a)


def solve_least_distance_interior(H: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fallback for degenerate problems (where the active-set method can cycle): an interior-point solve of
    ``min 1/2 ||z||^2 s.t. H z >= b`` with cvxpy + Clarabel (OSQP if Clarabel is unavailable).
    Returns ``(z, a)`` with a >= 0 the constraint multipliers (the dual QP's solution)."""
    import cvxpy as cp

    z = cp.Variable(H.shape[1])
    cons = [H @ z >= b]
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(z)), cons)
    if cp.CLARABEL in cp.installed_solvers():
        kwargs = dict(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, tol_ktratio=1e-9)
    else:
        kwargs = dict(solver=cp.OSQP, eps_abs=1e-10, eps_rel=1e-10, max_iter=200000, polish=True)
    try:
        prob.solve(**kwargs)
    except cp.error.SolverError as exc:
        raise QPError(f"interior-point fallback failed: {exc}") from exc
    if prob.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or z.value is None:
        raise QPError(f"interior-point fallback: {prob.status} (are the constraints compatible?)")
    return np.asarray(z.value), np.maximum(np.asarray(cons[0].dual_value), 0.0)
