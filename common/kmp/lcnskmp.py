"""Linearly constrained null-space KMP (LC-NS-KMP): paper Section II-B, eqs. (2)-(6), as corrected in
``math.md`` §3-§6.

Everything is float64. ``A = (K + gamma Sigma)^-1`` (gamma = lambda + beta) is never formed: ``K +
gamma Sigma`` is Cholesky-factored once and every product with A is a triangular solve. Neither K nor
Sigma is ever inverted.

Two ways to evaluate the model:

* the general path (:meth:`LCNSKMP.predict`, :meth:`~LCNSKMP.projector`, :meth:`~LCNSKMP.invert`,
  :meth:`~LCNSKMP.cov`) for arbitrary query inputs -- one Cholesky solve per call, plus the dual QP
  when constraints are given;
* the per-step path on the reference grid (:meth:`LCNSKMP.grid_step`, :meth:`~LCNSKMP.grid_invert`),
  what the actor calls every control step with ``s* = s_hat = s_n``: precomputed tables (math.md §6) so
  that one step costs O(O^2) without constraints, O(N F O) plus a small active-set QP when the
  constraints become active.

Conventions: ``s`` (N, I) reference inputs, ``mu`` (N, O) GMR means, ``sigma`` (N, O, O) GMR
covariances, stacked point-major. Constraints ``(G, c)`` mean ``G[n, f] @ eta(s_n) >= c[n, f]`` at every
grid input; ``G`` is (F, O) (shared by all points) or (N, F, O), ``c`` is (F,) or (N, F). Their validation,
feasibility check are in ``common/kmp/inputs.py``, the dual QP's tables in ``common/kmp/dual.py``.

One module of ~390 lines on purpose: every method is the same model's equation (2)-(6) on one Cholesky factor
and one dual QP state; the math parts it uses (kernels, inputs, the dual, the QP) are modules of their own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from khgrl.common.kmp.dual import dual_tables, gbar, gbar_t, least_distance_factor
from khgrl.common.kmp.inputs import (
    InfeasibleConstraintsError,
    as_2d,
    check_feasible,
    check_hyperparameters,
    check_reference,
    normalise_constraints,
)
from khgrl.common.kmp.kernels import RBF, Kernel, evaluate_kernel, kernel_diag
from khgrl.common.kmp.qp import QPError, solve_dual_qp, solve_least_distance_interior

__all__ = ["LCNSKMP", "InfeasibleConstraintsError", "QPError"]


@dataclass
class StepInfo:
    """What the last :meth:`LCNSKMP.grid_step` did with the constraints."""

    active_rows: int = 0  # constraint rows with alpha > 0 (0: KKT shortcut, the unconstrained step was feasible)
    qp_solved: bool = False


class LCNSKMP:
    """Linearly constrained null-space kernelized movement primitive.

    Args:
        s: (N, I) reference inputs (normalised time for a trajectory, I = 1).
        mu: (N, O) reference means (GMR).
        sigma: (N, O, O) reference covariances, symmetric positive definite.
        lam: lambda > 0, KMP regulariser.
        beta: beta > 0, null-space weight; gamma = lambda + beta.
        kernel: an :class:`~khgrl.common.kmp.kernels.RBF` or any callable ``k((n1, I), (n2, I)) -> (n1, n2)``
            that is positive definite on the inputs.
        constraints: optional ``(G, c)``: ``G @ eta >= c`` at every grid input (see module docstring).

    Raises:
        ValueError: wrong shapes, non-finite values, non-positive hyperparameters, non-PSD sigma.
        InfeasibleConstraintsError: the constraints admit no point at some grid input.
    """

    def __init__(
        self,
        s: np.ndarray,
        mu: np.ndarray,
        sigma: np.ndarray,
        *,
        lam: float,
        beta: float,
        kernel: Kernel | None = None,
        constraints: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        self.s, self.mu, sig = check_reference(s, mu, sigma)
        n, i = self.s.shape
        o = self.mu.shape[1]
        check_hyperparameters(lam, beta)
        self.sigma = sig
        self.lam, self.beta = float(lam), float(beta)
        self.gamma = self.lam + self.beta
        self.kernel: Kernel = kernel if kernel is not None else RBF()
        self.n_points, self.in_dim, self.out_dim = n, i, o

        # Gram matrix K = kmat (x) I_O and Sigma = blkdiag(sigma_n), point-major (math.md §1).
        kmat = evaluate_kernel(self.kernel, self.s, self.s)
        self._kmat = 0.5 * (kmat + kmat.T)
        self._kdiag = np.diag(self._kmat).copy()
        if np.any(self._kdiag <= 0):
            raise ValueError("kernel must satisfy k(s, s) > 0")
        K = np.kron(self._kmat, np.eye(o))
        Sigma = scipy.linalg.block_diag(*sig)
        try:
            self._chol = scipy.linalg.cho_factor(K + self.gamma * Sigma, lower=True, check_finite=False)
        except np.linalg.LinAlgError as exc:  # pragma: no cover - K PSD + gamma*Sigma PD is PD
            raise ValueError("K + gamma*Sigma is not positive definite: is the kernel positive definite?") from exc
        self._Sigma = Sigma

        # A mu and the grid mean eta0 = K A mu (the gamma-regularised KMP mean, xi = 0).
        self._a_mu = self._solve(self.mu.reshape(-1))
        self._eta0 = (self._kmat @ self._a_mu.reshape(n, o)).copy()

        # M = K A Sigma = Sigma - gamma Sigma A Sigma (from I - KA = gamma Sigma A), symmetric PSD by construction.
        W = scipy.linalg.solve_triangular(self._chol[0], Sigma, lower=True, check_finite=False)
        M = Sigma - self.gamma * (W.T @ W)
        self._M = 0.5 * (M + M.T)

        # Projector table on the grid: N(s_n) = beta [K A Sigma]_nn / k(s_n, s_n)  (math.md §4).
        M4 = self._M.reshape(n, o, n, o)
        blocks = M4[np.arange(n), :, np.arange(n), :]  # (N, O, O)
        self._proj = self.beta * blocks / self._kdiag[:, None, None]
        self._proj = 0.5 * (self._proj + np.swapaxes(self._proj, 1, 2))

        self._eta0.flags.writeable = False
        self._proj.flags.writeable = False
        self._G: np.ndarray | None = None
        self._H: np.ndarray | None = None  # least-distance factor, built only for the interior-point fallback
        self._last_active: list[int] = []  # warm start for the next grid step's QP
        self._last_alpha: np.ndarray | None = None  # multipliers of the last constrained grid step
        self._c: np.ndarray | None = None
        self.step_info = StepInfo()
        if constraints is not None:
            self._setup_constraints(*constraints)

    # ------------------------------------------------------------------ helpers
    def _solve(self, rhs: np.ndarray) -> np.ndarray:
        """A @ rhs = (K + gamma Sigma)^-1 rhs via the stored Cholesky factor."""
        return scipy.linalg.cho_solve(self._chol, rhs, check_finite=False)

    def _kron_rows(self, kvec: np.ndarray) -> np.ndarray:
        """(Q, N) kernel rows -> (Q*O, N*O) block rows k* = kvec (x) I_O."""
        return np.kron(kvec, np.eye(self.out_dim))

    def _check_query(self, s_star: np.ndarray) -> np.ndarray:
        return as_2d("s_star", s_star, self.in_dim)

    @property
    def constrained(self) -> bool:
        return self._G is not None

    @property
    def n_constraints(self) -> int:
        """F, constraints per grid point (0 without constraints)."""
        return 0 if self._G is None else self._G.shape[1]

    @property
    def constraints(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The hard constraints as normalised at construction, (G (N, F, O), c (N, F)), or None; read-only views."""
        if self._G is None:
            return None
        G, c = self._G.view(), self._c.view()
        G.flags.writeable = c.flags.writeable = False
        return G, c

    @property
    def grid_mean(self) -> np.ndarray:
        """(N, O) unconstrained grid mean K A mu (xi = 0); a read-only view."""
        return self._eta0

    @property
    def grid_projector(self) -> np.ndarray:
        """(N, O, O) projector table N(s_n) with s* = s_hat = s_n; a read-only view."""
        return self._proj

    # -------------------------------------------------------------- constraints
    def _setup_constraints(self, G: np.ndarray, c: np.ndarray) -> None:
        G, c = normalise_constraints(G, c, self.n_points, self.out_dim)
        check_feasible(G, c)
        self._G, self._c = G, c
        self._P, self._Q, self._q0 = dual_tables(self._M, G, c, self._eta0)

    def _gbar_t(self, v: np.ndarray) -> np.ndarray:
        """Gbar^T v for a point-major (N*O,) vector -> (N*F,)."""
        return gbar_t(self._G, v)

    def _gbar(self, alpha: np.ndarray) -> np.ndarray:
        """Gbar alpha for (N*F,) -> point-major (N*O,)."""
        return gbar(self._G, alpha)

    def _dual(self, q: np.ndarray, warm: list[int] | None = None) -> np.ndarray:
        """alpha* = argmin_{alpha>=0} 1/2 alpha^T Q alpha + q^T alpha (eq. 3, corrected; math.md §3).

        ``q`` is the constraint slack of the unconstrained grid trajectory; the constrained one is
        that trajectory + M Gbar alpha. Goldfarb-Idnani active set (exact, finite); for degenerate
        constraint sets where it fails, an interior-point solve of the least-distance form with
        H = Gbar^T R, M = R R^T (R built on first use).
        """
        try:
            alpha, self._last_active = solve_dual_qp(self._Q, q, warm)
            return alpha
        except (QPError, np.linalg.LinAlgError):
            if self._H is None:
                self._H = least_distance_factor(self._M, self._G)
            _, alpha = solve_least_distance_interior(self._H, -q)
            # feasibility, not complementarity: interior-point multipliers are large (~1e5) on such problems
            if np.min(self._Q @ alpha + q) < -1e-6 * max(1.0, float(np.max(np.abs(q)))):
                raise QPError("constraint QP unsolved by the active-set and interior-point methods") from None
            self._last_active = []
            return alpha

    # ------------------------------------------------------------ general path
    def _secondary(self, xi: np.ndarray | None, s_hat: np.ndarray | None):
        """Validate (xi, s_hat); returns (xi, s_hat (1, I)) or (None, None) when xi is absent or zero."""
        if xi is None:
            return None, None
        xi = np.asarray(xi, dtype=np.float64).reshape(-1)
        if xi.shape != (self.out_dim,) or not np.all(np.isfinite(xi)):
            raise ValueError(f"xi must be a finite ({self.out_dim},) vector, got {np.asarray(xi).shape}")
        if s_hat is None:
            raise ValueError(
                "xi given without s_hat: pass the secondary input s_hat (I,) (use projector() for s_hat = s*)"
            )
        s_hat = as_2d("s_hat", np.asarray(s_hat, dtype=np.float64).reshape(1, -1), self.in_dim)
        return xi, s_hat

    def predict(self, s_star: np.ndarray, xi: np.ndarray | None = None, s_hat: np.ndarray | None = None) -> np.ndarray:
        """Expectation E[eta(s*)] with one null-space action ``xi`` at one secondary input ``s_hat`` (eq. 4).

        E[eta(s*)] = k* A mu + k* A Sigma Gbar alpha + (beta/gamma)(k^* - k* A K^) K_^-1 xi,
        alpha from the dual QP (eq. 3) when constraints are given. Same semantics as ``lc-ns-kmp``'s
        ``predict_LCNS``; with ``xi=None`` this is the (constrained) gamma-regularised mean.

        Args:
            s_star: (Q, I) query inputs.
            xi: (O,) null-space action, or None.
            s_hat: (I,) secondary input, required with ``xi``.

        Returns:
            (Q, O) expectations.
        """
        s_star = self._check_query(s_star)
        xi, s_hat = self._secondary(xi, s_hat)
        n, o = self.n_points, self.out_dim
        kstar = evaluate_kernel(self.kernel, s_star, self.s)  # (Q, N)
        mean = kstar @ self._a_mu.reshape(n, o)
        grid = self._eta0.reshape(-1)
        if xi is not None:
            khat = evaluate_kernel(self.kernel, self.s, s_hat)[:, 0]  # (N,)
            k_low = float(evaluate_kernel(self.kernel, s_hat, s_hat)[0, 0])
            khat_star = evaluate_kernel(self.kernel, s_star, s_hat)[:, 0]  # (Q,)
            # A K^ K_^-1 xi with K^ = khat (x) I_O:  K^ xi = kron(khat, xi).
            a_khat_xi = self._solve(np.kron(khat, xi)) / k_low
            term = khat_star[:, None] * xi[None, :] / k_low - kstar @ a_khat_xi.reshape(n, o)
            mean = mean + (self.beta / self.gamma) * term
            # Unconstrained grid trajectory: K A mu + beta Sigma A K^ K_^-1 xi.
            grid = grid + self.beta * (self._Sigma @ a_khat_xi)
        if self.constrained:
            q = self._gbar_t(grid) - self._c.reshape(-1)
            if np.any(q < 0.0):
                alpha = self._dual(q)
                a_sigma_g_alpha = self._solve(self._Sigma @ self._gbar(alpha))
                mean = mean + kstar @ a_sigma_g_alpha.reshape(n, o)
        return mean

    def projector(self, s_star: np.ndarray) -> np.ndarray:
        """Soft null-space projector with s_hat = s* (eq. 5, math.md §4), shape (Q, O, O).

        N(s*) = (beta/gamma) (k(s*,s*) I - k* A k*^T) / k(s*,s*), symmetric positive definite and
        bounded by (beta/gamma) I. Uses k* A k*^T = V^T V with V = L^-1 k*^T (L the Cholesky factor).
        """
        s_star = self._check_query(s_star)
        o = self.out_dim
        kstar = evaluate_kernel(self.kernel, s_star, self.s)
        kss = kernel_diag(self.kernel, s_star)
        V = scipy.linalg.solve_triangular(self._chol[0], self._kron_rows(kstar).T, lower=True, check_finite=False)
        qcount = s_star.shape[0]
        V3 = V.reshape(-1, qcount, o)  # columns grouped per query
        kak = np.einsum("mqa,mqb->qab", V3, V3)
        proj = (self.beta / self.gamma) * (kss[:, None, None] * np.eye(o)[None] - kak) / kss[:, None, None]
        return 0.5 * (proj + np.swapaxes(proj, 1, 2))

    def invert(self, s_star: np.ndarray, p_h: np.ndarray) -> np.ndarray:
        """Human correction -> null-space action (eq. 6, alpha = 0, s_hat = s*), shape (Q, O).

        xi_h = N(s*)^-1 (P_h - k* A mu), solved as a symmetric O x O system per query.
        """
        s_star = self._check_query(s_star)
        p_h = as_2d("p_h", p_h, self.out_dim)
        if p_h.shape[0] != s_star.shape[0]:
            raise ValueError(f"p_h has {p_h.shape[0]} rows, s_star has {s_star.shape[0]}")
        n, o = self.n_points, self.out_dim
        kstar = evaluate_kernel(self.kernel, s_star, self.s)
        delta = p_h - kstar @ self._a_mu.reshape(n, o)
        proj = self.projector(s_star)
        return np.stack([scipy.linalg.solve(proj[k], delta[k], assume_a="pos") for k in range(len(delta))])

    def cov(self, s_star: np.ndarray) -> np.ndarray:
        """KMP predictive covariance (Huang et al. 2019, eq. 26, with gamma in place of lambda):
        cov(s*) = (N / gamma) (k(s*,s*) I - k* A k*^T), shape (Q, O, O).

        It is the projector up to a scalar: cov = (N / beta) k(s*,s*) N(s*).
        """
        s_star = self._check_query(s_star)
        kss = kernel_diag(self.kernel, s_star)
        return (self.n_points / self.beta) * kss[:, None, None] * self.projector(s_star)

    # ----------------------------------------------------------- per-step path
    def grid_step(self, n: int, xi: np.ndarray) -> np.ndarray:
        """One control step on the grid: eq. (5) at s* = s_hat = s_n with null-space action ``xi`` (O,).

        eta = eta0_n + N_n xi (O(O^2)); with constraints, the dual's linear term is updated in O(N F O)
        (q = q0 + (beta / k_nn) (M Gbar)[n]^T xi), alpha = 0 if q >= 0 (KKT shortcut), else a small
        active-set QP (Goldfarb-Idnani) that adds violated rows one at a time. ``self.step_info`` tells which happened.
        """
        if not 0 <= n < self.n_points:
            raise IndexError(f"grid index {n} outside [0, {self.n_points})")
        xi = np.asarray(xi, dtype=np.float64)
        if xi.shape != (self.out_dim,) or not np.isfinite(xi).all():
            raise ValueError(f"xi must be a finite ({self.out_dim},) vector, got shape {xi.shape}")
        eta = self._eta0[n] + self._proj[n] @ xi
        if self._G is None:
            return eta
        o = self.out_dim
        rows = self._P[n * o : (n + 1) * o]  # (O, NF) = ((M Gbar)[n-block])
        q = self._q0 + (self.beta / self._kdiag[n]) * (xi @ rows)
        info = self.step_info
        if q.min() >= 0.0:
            info.active_rows, info.qp_solved = 0, False
            self._last_alpha = None
            return eta
        # Warm start only from a large previous active set (e.g. the mean itself constrained over a stretch):
        # a small one has usually moved with the step index, and re-adding 1-3 rows cold is cheaper.
        warm = self._last_active if len(self._last_active) >= 4 else None
        alpha = self._dual(q, warm)
        self._last_alpha = alpha
        nz = np.flatnonzero(alpha)
        info.active_rows, info.qp_solved = int(nz.size), True
        return eta + rows[:, nz] @ alpha[nz]

    def grid_invert(self, n: int, p_h: np.ndarray) -> np.ndarray:
        """Eq. (6) on the grid: xi_h = N_n^-1 (P_h - eta0_n), from the tabulated projector (alpha = 0)."""
        if not 0 <= n < self.n_points:
            raise IndexError(f"grid index {n} outside [0, {self.n_points})")
        p_h = np.asarray(p_h, dtype=np.float64)
        if p_h.shape != (self.out_dim,) or not np.isfinite(p_h).all():
            raise ValueError(f"p_h must be a finite ({self.out_dim},) vector, got shape {p_h.shape}")
        return scipy.linalg.solve(self._proj[n], np.asarray(p_h, dtype=np.float64) - self._eta0[n], assume_a="pos")

    def grid_invert_constrained(self, n: int, p_h: np.ndarray, *, tol: float = 1e-10, max_iter: int = 10) -> np.ndarray:
        """xi such that :meth:`grid_step` (with the hard constraints) gives ``p_h`` (math.md §4).

        Starts from eq. (6) (alpha = 0). While constraints are active the forward map is piecewise affine in
        xi: for a fixed active set A, alpha_A = -Q_AA^-1 q_A(xi), so dP/dxi = N_n - (beta/k_nn) P_nA Q_AA^-1 P_nA^T.
        Newton steps on it are exact once A is right (a least-squares step when P_h is pinned by a
        constraint at this very point). Returns the best xi found.
        """
        p_h = np.asarray(p_h, dtype=np.float64)
        xi = self.grid_invert(n, p_h)
        if self._G is None:
            return xi
        o = self.out_dim
        rows = self._P[n * o : (n + 1) * o]
        best, best_err = xi, np.inf
        for _ in range(max_iter):
            p = self.grid_step(n, xi)
            err = float(np.max(np.abs(p - p_h)))
            if err < best_err:
                best, best_err = xi, err
            if err <= tol or self.step_info.active_rows == 0:
                break
            act = [i for i in self._last_active if self._last_alpha is not None and self._last_alpha[i] > 0]
            pa = rows[:, act]
            q_inv_pa = np.linalg.lstsq(self._Q[np.ix_(act, act)], pa.T, rcond=1e-12)[0]
            jac = self._proj[n] - (self.beta / self._kdiag[n]) * pa @ q_inv_pa
            xi = xi + np.linalg.lstsq(jac, p_h - p, rcond=1e-12)[0]
        return best

    def grid_constraint_term(self, n: int) -> np.ndarray:
        """[k* A Sigma Gbar alpha] at s_n for the alpha of the last :meth:`grid_step` (zero if none was active)."""
        if self._G is None or self._last_alpha is None:
            return np.zeros(self.out_dim)
        nz = np.flatnonzero(self._last_alpha)
        o = self.out_dim
        return self._P[n * o : (n + 1) * o, nz] @ self._last_alpha[nz]

    def grid_index(self, s_star: float) -> int:
        """Nearest grid index to a scalar input (I = 1)."""
        return int(np.argmin(np.abs(self.s[:, 0] - s_star)))
