"""LC-NS-KMP (khgrl.common.kmp.lcnskmp): every check of math.md §7, plus input validation.

Reference computations here are deliberately independent of the implementation: the primal problem
(paper eq. 2) is solved in weight space with cvxpy for a kernel that *is* a finite feature map, and the
kernelised formulas are recomputed with plain numpy inverses on small problems.

Some checks read private attributes of the model (``_Q``, ``_dual``, ``_G``): the dual QP's Hessian and
multipliers are not part of the public API, but math.md §7 asks for complementarity on exactly them.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from khgrl.common.kmp.kernels import RBF
from khgrl.common.kmp.lcnskmp import LCNSKMP, InfeasibleConstraintsError
from khgrl.common.kmp.qp import lcp_residual

from kmp_problems import BETA, BOX_C, BOX_G, LAM, PRECISION, Reference, dense_A, make_reference

GAMMA = LAM + BETA
N_REF = 40  # size of the shared ``ref`` fixture
HYP = settings(max_examples=40, deadline=None)

# Box that the gamma-regularised mean satisfies (|x| <= 1.05, |y| <= 0.6) but that moderate actions
# xi push the trajectory out of: a mix of KKT-shortcut steps and QP steps.
MID_C = np.array([-1.05, -1.05, -0.6, -0.6])


def xis(scale: float):
    """Null-space actions in [-scale, scale]^2."""
    return st.lists(st.floats(-scale, scale, allow_nan=False, allow_infinity=False), min_size=2, max_size=2).map(
        np.array
    )


@pytest.fixture(scope="session")
def mid_model(ref: Reference, kernel: RBF) -> LCNSKMP:
    return LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(BOX_G, MID_C))


@pytest.fixture(scope="session")
def halfplane_model(ref: Reference, kernel: RBF) -> LCNSKMP:
    """Per-point constraints (N, F, O): a rotating half-plane that cuts the mean at every other point,
    plus a shared far-away row."""
    n = ref.n
    th = np.linspace(0, 2 * np.pi, n)
    G = np.zeros((n, 2, 2))
    G[:, 0] = np.c_[np.cos(th), np.sin(th)]
    G[:, 1] = [0.0, 1.0]
    c = np.zeros((n, 2))
    c[:, 0] = np.einsum("no,no->n", G[:, 0], ref.mu) + np.where(np.arange(n) % 2 == 0, 0.05, -0.5)
    c[:, 1] = -10.0
    return LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(G, c))


@pytest.fixture(scope="session")
def var_model(ref: Reference) -> LCNSKMP:
    """RBF with variance 3 (k(s, s) != 1): exercises every K_low^-1 = 1 / k(s_hat, s_hat)."""
    k = RBF(length_scale=RBF.from_precision(PRECISION).length_scale, variance=3.0)
    return LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=k)


def _constraint_slack(m: LCNSKMP, eta_grid: np.ndarray) -> np.ndarray:
    """(N, F) slack G_n eta(s_n) - c_n of a grid trajectory."""
    return np.einsum("nfo,no->nf", m._G, eta_grid) - m._c


# =========================================================================== primal = dual
class FeatureKernel:
    """k(a, b) = phi(a) phi(b)^T with B Gaussian bumps in s: a finite feature map, so the kernelised dual
    and the weight-space primal describe exactly the same model. k(s, s) != 1 (K_low matters)."""

    def __init__(self, n_basis: int = 40, width: float = 0.08) -> None:
        self.centers = np.linspace(-0.2, 1.2, n_basis)
        self.width = width

    def phi(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64).reshape(-1, 1)
        return np.exp(-0.5 * ((s - self.centers[None, :]) / self.width) ** 2)

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return self.phi(a) @ self.phi(b).T


def primal_eta(feat, ref, s_star, *, xi=None, s_hat=None, G=None, c=None) -> np.ndarray:
    """Paper eq. (2) in weight space, solved by cvxpy (CLARABEL):

    min_w 1/2 sum_n (Theta_n^T w - mu_n)^T Sigma_n^-1 (.) + lam/2 ||w||^2 + beta/2 ||w - w_hat||^2
    s.t. G_n Theta_n^T w >= c_n,   w_hat = Phi_hat K_low^-1 xi,  Theta(s) = phi(s) (x) I_O.
    Returns eta(s*) = Theta(s*)^T w, shape (Q, O).
    """
    o, b = ref.o, feat.centers.size
    theta = np.kron(feat.phi(ref.s), np.eye(o))  # (N O, B O); row block n is Theta_n^T
    # r^T Sigma^-1 r = ||L^T r||^2 with L L^T = Sigma_n^-1 (inverse of a 2x2 block: fine here)
    w_res = scipy.linalg.block_diag(*[np.linalg.cholesky(np.linalg.inv(S)).T for S in ref.sigma])
    if xi is None:
        w_hat = np.zeros(b * o)
    else:
        s_hat = np.atleast_2d(s_hat)
        k_low = float(feat(s_hat, s_hat)[0, 0])
        w_hat = np.kron(feat.phi(s_hat).T, np.eye(o)) @ np.asarray(xi) / k_low
    w = cp.Variable(b * o)
    objective = (
        0.5 * cp.sum_squares(w_res @ (theta @ w - ref.mu.reshape(-1)))
        + 0.5 * LAM * cp.sum_squares(w)
        + 0.5 * BETA * cp.sum_squares(w - w_hat)
    )
    cons = []
    if G is not None:
        G3 = np.broadcast_to(G, (ref.n, *G.shape[-2:])) if G.ndim == 2 else G
        c2 = np.broadcast_to(c, G3.shape[:2])
        gbar_t = scipy.linalg.block_diag(*G3)  # (N F, N O)
        cons = [gbar_t @ (theta @ w) >= c2.reshape(-1)]
    prob = cp.Problem(cp.Minimize(objective), cons)
    prob.solve(solver="CLARABEL", tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12, tol_ktratio=1e-10)
    assert prob.status == "optimal", prob.status
    return (np.kron(feat.phi(s_star), np.eye(o)) @ w.value).reshape(-1, o)


@pytest.fixture(scope="module")
def pd_setup():
    ref = make_reference(50, seed=1)
    feat = FeatureKernel()
    s_star = np.r_[ref.s, np.linspace(-0.05, 1.05, 31)[:, None]]  # grid and off-grid queries
    return ref, feat, s_star


def _halfplanes(ref):
    th = np.linspace(0, 2 * np.pi, ref.n)
    G = np.stack([np.c_[np.cos(th), np.sin(th)], np.c_[-np.sin(th), np.cos(th)]], axis=1)  # (N, 2, 2)
    c = np.einsum("nfo,no->nf", G, ref.mu) + np.array([0.04, -1.0])
    return G, c


PD_CASES = {
    "mean": dict(),
    "xi_offgrid": dict(xi=np.array([4.0, -3.0]), s_hat=np.array([0.33])),
    "box_mean": dict(G=BOX_G, c=BOX_C),
    "box_xi": dict(G=BOX_G, c=BOX_C, xi=np.array([40.0, 30.0]), s_hat=np.array([0.5])),
    "box_xi_edge": dict(G=BOX_G, c=BOX_C, xi=np.array([-25.0, 60.0]), s_hat=np.array([0.02])),
    "halfplanes": dict(G="halfplanes"),
    "halfplanes_xi": dict(G="halfplanes", xi=np.array([-10.0, 8.0]), s_hat=np.array([0.71])),
}


@pytest.mark.parametrize("case", list(PD_CASES))
def test_primal_equals_dual(pd_setup, case):
    ref, feat, s_star = pd_setup
    kw = dict(PD_CASES[case])
    if isinstance(kw.get("G"), str):
        kw["G"], kw["c"] = _halfplanes(ref)
    constraints = (kw["G"], kw["c"]) if "G" in kw else None
    m = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=feat, constraints=constraints)
    eta_dual = m.predict(s_star, kw.get("xi"), kw.get("s_hat"))
    eta_primal = primal_eta(feat, ref, s_star, **kw)
    err = np.abs(eta_dual - eta_primal).max()
    assert err <= 1e-6, f"primal vs dual max |d eta| = {err:.3g}"
    if constraints is not None:
        # the constraints really are active: the unconstrained solution violates them on the grid
        free = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=feat)
        assert _constraint_slack(m, free.predict(ref.s, kw.get("xi"), kw.get("s_hat"))).min() < -0.02
        assert _constraint_slack(m, m.predict(ref.s, kw.get("xi"), kw.get("s_hat"))).min() >= -1e-8


def test_primal_equals_dual_grid_step(pd_setup):
    """The tabulated constrained per-step path against the primal, at s* = s_hat = s_n."""
    ref, feat, _ = pd_setup
    m = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=feat, constraints=(BOX_G, BOX_C))
    for n, xi in [(3, np.array([30.0, -50.0])), (25, np.array([60.0, 10.0])), (44, np.array([0.0, 0.0]))]:
        eta = m.grid_step(n, xi)
        ref_eta = primal_eta(feat, ref, ref.s[n : n + 1], xi=xi, s_hat=ref.s[n], G=BOX_G, c=BOX_C)[0]
        assert np.abs(eta - ref_eta).max() <= 1e-6


# ====================================================== A = (K + gamma Sigma)^-1, dense formulas
def test_mean_uses_gamma_not_lambda(ref, kernel, model):
    q = np.r_[ref.s, np.linspace(0.01, 0.99, 17)[:, None]]
    A = dense_A(ref, kernel(ref.s, ref.s), GAMMA)
    kstar = np.kron(kernel(q, ref.s), np.eye(2))
    expected = (kstar @ A @ ref.mu.reshape(-1)).reshape(-1, 2)
    got = model.predict(q)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10)
    # and the lambda-KMP mean (the paper's typo) is measurably different on this problem
    wrong = (kstar @ dense_A(ref, kernel(ref.s, ref.s), LAM) @ ref.mu.reshape(-1)).reshape(-1, 2)
    assert np.abs(got - wrong).max() > 3e-3  # measured 6.6e-3 here (small Sigma); ~0.17 on unit-scale data


@pytest.mark.parametrize("variance", [1.0, 3.0, 0.25])
def test_predict_with_xi_matches_dense_formula(ref, variance):
    """E[eta(s*)] = k* A mu + (beta/gamma)(k^* - k* A K^) K_low^-1 xi, K_low = k(s_hat, s_hat) I."""
    k = RBF(length_scale=0.1, variance=variance)
    m = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=k)
    q = np.r_[ref.s[::3], np.linspace(0.0, 1.0, 13)[:, None] + 0.004]
    s_hat = np.array([[0.41]])
    xi = np.array([3.0, -7.0])
    A = dense_A(ref, k(ref.s, ref.s), GAMMA)
    kstar = np.kron(k(q, ref.s), np.eye(2))
    khat_big = np.kron(k(ref.s, s_hat), np.eye(2))  # K^ (N O, O)
    k_low = k(s_hat, s_hat)[0, 0]
    khat_star = k(q, s_hat)[:, 0]
    mean = (kstar @ A @ ref.mu.reshape(-1)).reshape(-1, 2)
    ns = (BETA / GAMMA) * (khat_star[:, None] * xi[None, :] - (kstar @ A @ khat_big @ xi).reshape(-1, 2)) / k_low
    np.testing.assert_allclose(m.predict(q, xi, s_hat[0]), mean + ns, rtol=0, atol=1e-10)


def test_dual_matrices_match_dense_formulas(ref, kernel, box_model):
    """Q = Gbar^T K A Sigma Gbar and q0 = Gbar^T K A mu - Cbar (math.md §3, eq. 3 corrected)."""
    K = np.kron(kernel(ref.s, ref.s), np.eye(2))
    A = dense_A(ref, kernel(ref.s, ref.s), GAMMA)
    Sigma = scipy.linalg.block_diag(*ref.sigma)
    gbar = scipy.linalg.block_diag(*[BOX_G.T] * ref.n)  # (N O, N F)
    Q = gbar.T @ K @ A @ Sigma @ gbar
    q0 = gbar.T @ K @ A @ ref.mu.reshape(-1) - np.tile(BOX_C, ref.n)
    np.testing.assert_allclose(box_model._Q, Q, rtol=0, atol=1e-10 * np.abs(Q).max())
    np.testing.assert_allclose(box_model._q0, q0, rtol=0, atol=1e-10)


def test_cov_matches_dense_formula(ref, kernel, model):
    q = np.linspace(0, 1, 9)[:, None] + 0.01
    A = dense_A(ref, kernel(ref.s, ref.s), GAMMA)
    kstar = np.kron(kernel(q, ref.s), np.eye(2))
    for j in range(q.shape[0]):
        ks = kstar[2 * j : 2 * j + 2]
        expected = (ref.n / GAMMA) * (np.eye(2) - ks @ A @ ks.T)
        np.testing.assert_allclose(model.cov(q[j : j + 1])[0], expected, rtol=1e-8, atol=1e-12)


# ======================================================================= round trips (alpha = 0)
@HYP
@given(s=st.floats(0.0, 1.0), xi=xis(50.0))
def test_roundtrip_xi_to_p_to_xi_offgrid(model, loose_model, var_model, s, xi):
    for m in (model, loose_model, var_model):
        p = m.predict([[s]], xi, [s])
        xi_hat = m.invert([[s]], p)[0]
        assert np.abs(xi_hat - xi).max() <= 1e-9 * max(1.0, np.abs(xi).max())


@HYP
@given(n=st.integers(0, N_REF - 1), xi=xis(50.0))
def test_roundtrip_xi_to_p_to_xi_grid(model, loose_model, var_model, n, xi):
    for m in (model, loose_model, var_model):
        p = m.grid_step(n, xi)
        assert np.abs(m.grid_invert(n, p) - xi).max() <= 1e-9 * max(1.0, np.abs(xi).max())
        # cross path: tabulated forward, general inverse
        assert np.abs(m.invert(m.s[n : n + 1], p[None])[0] - xi).max() <= 1e-9 * max(1.0, np.abs(xi).max())


@HYP
@given(s=st.floats(0.0, 1.0), delta=xis(0.5))
def test_roundtrip_p_to_xi_to_p_offgrid(model, loose_model, var_model, s, delta):
    for m in (model, loose_model, var_model):
        p_h = m.predict([[s]])[0] + delta  # a human correction near the current mean
        xi = m.invert([[s]], p_h[None])[0]
        np.testing.assert_allclose(m.predict([[s]], xi, [s])[0], p_h, rtol=0, atol=1e-9)


@HYP
@given(n=st.integers(0, N_REF - 1), delta=xis(0.5))
def test_roundtrip_p_to_xi_to_p_grid(model, loose_model, var_model, n, delta):
    for m in (model, loose_model, var_model):
        p_h = m.grid_mean[n] + delta
        xi = m.grid_invert(n, p_h)
        np.testing.assert_allclose(m.grid_step(n, xi), p_h, rtol=0, atol=1e-9)


def test_inactive_constraints_take_kkt_shortcut(loose_model):
    rng = np.random.default_rng(0)
    for _ in range(20):
        loose_model.grid_step(int(rng.integers(N_REF)), rng.uniform(-50, 50, 2))
        assert loose_model.step_info.active_rows == 0 and not loose_model.step_info.qp_solved


# ================================================================================== projector
def test_projector_symmetric_pd_bounded(model, var_model):
    q = np.r_[model.s, np.linspace(-0.3, 1.3, 57)[:, None]]
    for m in (model, var_model):
        P = m.projector(q)
        np.testing.assert_array_equal(P, np.swapaxes(P, 1, 2))
        eig = np.linalg.eigvalsh(P)
        assert eig.min() > 0
        assert eig.max() <= BETA / GAMMA * (1 + 1e-12)
        G = m.grid_projector
        np.testing.assert_array_equal(G, np.swapaxes(G, 1, 2))
        assert np.linalg.eigvalsh(G).min() > 0


def test_projector_far_from_data_is_beta_over_gamma(model):
    """No reference data near s*: nothing pins the trajectory, N -> (beta/gamma) I."""
    np.testing.assert_allclose(model.projector([[5.0], [-4.0]]), np.broadcast_to(BETA / GAMMA * np.eye(2), (2, 2, 2)),
                               atol=1e-12)


def test_projector_loewner_bounded_by_beta_sigma_on_grid(ref, model):
    """k(s, s) = 1: N(s_n) <= beta Sigma_n (math.md §4)."""
    gap = np.linalg.eigvalsh(BETA * ref.sigma - model.grid_projector)
    scale = np.linalg.eigvalsh(BETA * ref.sigma).max(axis=1)
    assert np.all(gap.min(axis=1) >= -1e-12 * scale)


@pytest.mark.parametrize("variance", [0.2, 3.0])
def test_projector_loewner_bound_general_variance(ref, variance):
    """For k(s, s) != 1 the bound is N(s_n) <= beta Sigma_n / k(s_n, s_n)  (N_n = beta [K A Sigma]_nn / k_nn
    and K A Sigma <= Sigma). With variance < 1 the unscaled beta Sigma_n bound of math.md §4 does not hold."""
    k = RBF(length_scale=0.1, variance=variance)
    m = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=k)
    gap = np.linalg.eigvalsh(BETA * ref.sigma / variance - m.grid_projector)
    assert np.all(gap.min(axis=1) >= -1e-12 * np.abs(gap).max())


def test_projector_vanishes_where_sigma_vanishes(ref, kernel, model):
    window = np.arange(15, 25)
    sigma = ref.sigma.copy()
    sigma[window] *= 1e-6
    m = LCNSKMP(ref.s, ref.mu, sigma, lam=LAM, beta=BETA, kernel=kernel)
    before = np.linalg.eigvalsh(model.grid_projector[window]).max(axis=1)
    after = np.linalg.eigvalsh(m.grid_projector[window]).max(axis=1)
    assert np.all(after <= 1e-4 * before)  # measured ratio ~1e-5: the 'before' side is kernel-limited
    assert np.all(np.linalg.eigvalsh(BETA * sigma[window] - m.grid_projector[window]) >= -1e-15)
    # the general (off-grid) projector shrinks too, between the shrunk grid points
    mid = 0.5 * (ref.s[window[:-1]] + ref.s[window[1:]])
    shrink = np.linalg.eigvalsh(m.projector(mid)).max(axis=1) / np.linalg.eigvalsh(model.projector(mid)).max(axis=1)
    assert np.all(shrink < 1e-2)
    # and elsewhere it is essentially unchanged
    far = np.r_[np.arange(0, 6), np.arange(34, 40)]
    for n in far:
        scale = np.linalg.eigvalsh(model.grid_projector[n]).max()
        np.testing.assert_allclose(m.grid_projector[n], model.grid_projector[n], rtol=0, atol=0.05 * scale)


# ============================================================== grid feasibility, complementarity
@HYP
@given(n=st.integers(0, N_REF - 1), xi=xis(60.0))
def test_grid_step_feasible(box_model, mid_model, halfplane_model, n, xi):
    for m in (box_model, mid_model, halfplane_model):
        eta = m.grid_step(n, xi)
        assert np.all(m._G[n] @ eta >= m._c[n] - 1e-8)
        traj = m.predict(m.s, xi, m.s[n])  # the full constrained grid trajectory
        assert _constraint_slack(m, traj).min() >= -1e-8
        # tabulated per-step result equals the direct formula (constraints active or not)
        np.testing.assert_allclose(eta, traj[n], rtol=0, atol=1e-10)


def test_mid_model_mixes_shortcut_and_qp_steps(mid_model):
    """Guard for the feasibility test above: with MID_C both branches of grid_step are exercised."""
    rng = np.random.default_rng(1)
    solved = []
    for _ in range(60):
        mid_model.grid_step(int(rng.integers(N_REF)), rng.uniform(-60, 60, 2))
        solved.append(mid_model.step_info.qp_solved)
    assert 0 < sum(solved) < len(solved)


@pytest.mark.parametrize("which", ["box_model", "mid_model", "halfplane_model"])
def test_complementarity(request, ref, kernel, which):
    """alpha >= 0, slack w = Q alpha + q >= 0, alpha_i w_i = 0, and w is the slack of the model's own
    constrained grid trajectory (so eta = eta_free + M Gbar alpha)."""
    m = request.getfixturevalue(which)
    K = np.kron(kernel(ref.s, ref.s), np.eye(2))
    A = dense_A(ref, kernel(ref.s, ref.s), GAMMA)
    Sigma = scipy.linalg.block_diag(*ref.sigma)
    gbar = scipy.linalg.block_diag(*[g.T for g in m._G])
    rng = np.random.default_rng(2)
    n_active = 0
    for _ in range(12):
        n = int(rng.integers(ref.n))
        xi = rng.uniform(-60, 60, 2)
        khat = np.kron(kernel(ref.s, ref.s[n : n + 1]), np.eye(2))
        q = gbar.T @ (K @ A @ ref.mu.reshape(-1) + BETA * Sigma @ A @ khat @ xi) - m._c.reshape(-1)
        alpha = m._dual(q)
        w = m._Q @ alpha + q
        assert lcp_residual(m._Q, q, alpha) <= 1e-9 * max(1.0, np.abs(q).max())
        assert alpha.min() >= 0 and np.abs(alpha * w).max() <= 1e-9
        slack = _constraint_slack(m, m.predict(ref.s, xi, ref.s[n])).reshape(-1)
        np.testing.assert_allclose(slack, w, rtol=0, atol=1e-8)
        n_active += int(np.any(alpha > 0))
    assert n_active > 0


def test_grid_episode_with_warm_starts(ref, kernel):
    """A whole episode n = 0..N-1 on a fresh model (warm start carried from step to step)."""
    m = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(BOX_G, MID_C))
    rng = np.random.default_rng(3)
    for n in range(ref.n):
        xi = rng.uniform(-60, 60, 2)
        eta = m.grid_step(n, xi)
        assert np.all(BOX_G @ eta >= MID_C - 1e-8)
        np.testing.assert_allclose(eta, m.predict(ref.s[n : n + 1], xi, ref.s[n])[0], rtol=0, atol=1e-10)


# ======================================================================= tabulated = direct formula
def test_grid_mean_is_direct(ref, kernel, model, box_model):
    A = dense_A(ref, kernel(ref.s, ref.s), GAMMA)
    K = np.kron(kernel(ref.s, ref.s), np.eye(2))
    expected = (K @ A @ ref.mu.reshape(-1)).reshape(-1, 2)
    np.testing.assert_allclose(model.grid_mean, expected, rtol=0, atol=1e-10)
    np.testing.assert_allclose(model.grid_mean, model.predict(ref.s), rtol=0, atol=1e-12)
    # with constraints the table still holds the unconstrained mean (alpha enters per step)
    np.testing.assert_allclose(box_model.grid_mean, model.grid_mean, rtol=0, atol=1e-14)


def test_grid_projector_is_direct(ref, model, var_model, box_model):
    for m in (model, var_model, box_model):
        np.testing.assert_allclose(m.grid_projector, m.projector(ref.s), rtol=1e-9, atol=1e-15)


@HYP
@given(n=st.integers(0, N_REF - 1), xi=xis(60.0))
def test_grid_step_equals_predict(model, loose_model, var_model, mid_model, box_model, n, xi):
    for m in (model, loose_model, var_model, mid_model, box_model):
        np.testing.assert_allclose(m.grid_step(n, xi), m.predict(m.s[n : n + 1], xi, m.s[n])[0], rtol=0, atol=1e-10)


@HYP
@given(n=st.integers(0, N_REF - 1), delta=xis(1.0))
def test_grid_invert_equals_invert(model, var_model, box_model, n, delta):
    for m in (model, var_model, box_model):
        p_h = m.grid_mean[n] + delta
        np.testing.assert_allclose(m.grid_invert(n, p_h), m.invert(m.s[n : n + 1], p_h[None])[0], rtol=1e-9, atol=1e-9)


def test_tables_cannot_be_corrupted_through_accessors(ref, kernel):
    """Writing into what grid_mean / grid_projector return must not change the model (either the write is
    refused, or it hits a copy)."""
    m = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel)
    xi = np.array([2.0, -1.0])
    before = m.grid_step(5, xi).copy()
    for table in (m.grid_mean, m.grid_projector):
        try:
            table[5] = 123.0
        except ValueError:
            pass
    np.testing.assert_array_equal(m.grid_step(5, xi), before)
    np.testing.assert_allclose(m.grid_mean[5], m.predict(ref.s[5:6])[0], rtol=0, atol=1e-12)


def test_projector_equals_linear_part_of_predict(model, var_model):
    """N(s*) xi = predict(s*, xi, s*) - predict(s*): the projector is the map the action goes through."""
    rng = np.random.default_rng(4)
    for m in (model, var_model):
        for s in rng.uniform(0, 1, 5):
            xi = rng.uniform(-20, 20, 2)
            lhs = m.projector([[s]])[0] @ xi
            np.testing.assert_allclose(lhs, m.predict([[s]], xi, [s])[0] - m.predict([[s]])[0], rtol=0, atol=1e-11)


# ==================================================================================== bad input
def _kw(ref, **over):
    kw = dict(s=ref.s, mu=ref.mu, sigma=ref.sigma, lam=LAM, beta=BETA, kernel=RBF(0.1))
    kw.update(over)
    return kw


def _build(kw):
    kw = dict(kw)
    return LCNSKMP(kw.pop("s"), kw.pop("mu"), kw.pop("sigma"), **kw)


def _nan_at(a, idx):
    a = np.array(a, dtype=np.float64)
    a[idx] = np.nan
    return a


def _bad_cases(ref):
    n = ref.n
    nonsym = ref.sigma.copy()
    nonsym[4, 0, 1] += 1e-3
    indefinite = ref.sigma.copy()
    indefinite[7] = np.array([[1.0, 2.0], [2.0, 1.0]])
    singular = ref.sigma.copy()
    singular[9] = np.zeros((2, 2))
    return {
        "s_3d": dict(s=ref.s[:, :, None]),
        "s_rows": dict(s=ref.s[:-1]),
        "mu_rows": dict(mu=ref.mu[:-1]),
        "mu_1d": dict(mu=ref.mu[:, 0]),
        "sigma_2d": dict(sigma=ref.sigma[:, 0, :]),
        "sigma_rows": dict(sigma=ref.sigma[:-1]),
        "sigma_not_square": dict(sigma=np.zeros((n, 2, 3))),
        "sigma_wrong_o": dict(sigma=np.broadcast_to(np.eye(3), (n, 3, 3))),
        "s_nan": dict(s=_nan_at(ref.s, (3, 0))),
        "mu_nan": dict(mu=_nan_at(ref.mu, (5, 1))),
        "mu_inf": dict(mu=np.where(np.arange(n)[:, None] == 2, np.inf, ref.mu)),
        "sigma_nan": dict(sigma=_nan_at(ref.sigma, (6, 1, 1))),
        "sigma_nonsym": dict(sigma=nonsym),
        "sigma_indefinite": dict(sigma=indefinite),
        "sigma_singular": dict(sigma=singular),
        "lam_zero": dict(lam=0.0),
        "lam_negative": dict(lam=-1.0),
        "lam_nan": dict(lam=np.nan),
        "beta_zero": dict(beta=0.0),
        "beta_negative": dict(beta=-0.5),
        "beta_inf": dict(beta=np.inf),
    }


@pytest.mark.parametrize("case", list(_bad_cases(make_reference(40))))
def test_bad_constructor_input(ref, case):
    with pytest.raises(ValueError):
        _build(_kw(ref, **_bad_cases(ref)[case]))


def test_bad_constructor_messages(ref):
    with pytest.raises(ValueError, match="symmetric"):
        _build(_kw(ref, **_bad_cases(ref)["sigma_nonsym"]))
    with pytest.raises(ValueError, match="positive definite"):
        _build(_kw(ref, **_bad_cases(ref)["sigma_indefinite"]))
    with pytest.raises(ValueError, match="NaN"):
        _build(_kw(ref, **_bad_cases(ref)["mu_nan"]))
    with pytest.raises(ValueError, match="lam"):
        _build(_kw(ref, lam=0.0))
    with pytest.raises(ValueError, match="beta"):
        _build(_kw(ref, beta=-1.0))


def test_bad_predict_input(model):
    s = model.s[:3]
    with pytest.raises(ValueError):
        model.predict(s, np.array([1.0, 2.0, 3.0]), [0.5])  # xi (3,) for O = 2
    with pytest.raises(ValueError):
        model.predict(s, np.array([1.0]), [0.5])
    with pytest.raises(ValueError):
        model.predict(s, np.array([np.nan, 1.0]), [0.5])
    with pytest.raises(ValueError, match="s_hat"):
        model.predict(s, np.array([1.0, 2.0]))  # xi without s_hat
    with pytest.raises(ValueError):
        model.predict(s, np.array([1.0, 2.0]), [0.5, 0.6])  # s_hat with I = 2
    with pytest.raises(ValueError):
        model.predict(s, np.array([1.0, 2.0]), [np.nan])
    with pytest.raises(ValueError):
        model.predict(np.zeros((3, 2)))  # s* with I = 2
    with pytest.raises(ValueError):
        model.predict(np.array([[np.nan]]))
    with pytest.raises(ValueError):
        model.projector(np.zeros((3, 2)))
    with pytest.raises(ValueError):
        model.invert(s, np.zeros((2, 2)))  # p_h rows != s* rows
    with pytest.raises(ValueError):
        model.invert(s, np.zeros((3, 3)))  # p_h with O = 3


def test_infeasible_constraints(ref, kernel):
    G = np.array([[1.0, 0.0], [-1.0, 0.0]])  # x >= 1 and x <= 0
    c = np.array([1.0, 0.0])
    with pytest.raises(InfeasibleConstraintsError):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(G, c))
    assert issubclass(InfeasibleConstraintsError, ValueError)


def test_infeasible_at_one_point_only(ref, kernel):
    G = np.broadcast_to(np.array([[1.0, 0.0], [-1.0, 0.0]]), (ref.n, 2, 2)).copy()
    c = np.tile([-1.0, -1.0], (ref.n, 1))  # |x| <= 1 ...
    c[17] = [1.0, 0.0]  # ... except x >= 1 and x <= 0 at point 17
    with pytest.raises(InfeasibleConstraintsError, match="17"):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(G, c))


def test_feasible_but_degenerate_constraints_accepted(ref, kernel):
    """x >= 0.2 and x <= 0.2 (an equality at every grid point) is feasible: the constructor accepts it and
    predict must enforce it. The 80 rows are degenerate: with a smooth kernel, the 40 neighbouring equality
    rows span only the kernel's numerical rank and the active-set method cycles; the interior-point fallback
    reaches |x - 0.2| = 1.5e-8 (measured); lc_ns_kmp (PIQP) reaches 1.1e-8 here."""
    G = np.array([[1.0, 0.0], [-1.0, 0.0]])
    c = np.array([0.2, -0.2])
    m = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(G, c))
    np.testing.assert_allclose(m.predict(ref.s)[:, 0], 0.2, atol=5e-8)


@pytest.mark.parametrize(
    "G,c",
    [
        (np.ones((3, 2)), np.ones(4)),  # F mismatch
        (np.ones((3, 3)), np.ones(3)),  # O mismatch
        (np.ones((3, 2)), np.ones((3, 1))),  # c must be (F,)
        (np.ones((N_REF + 1, 3, 2)), np.ones((N_REF + 1, 3))),  # N mismatch
        (np.ones((N_REF, 3, 2)), np.ones((N_REF, 4))),  # per-point F mismatch
        (np.ones((N_REF, 3, 2)), np.ones(3)),  # per-point G with shared c
        (np.ones(2), np.ones(1)),  # 1-D G
        (np.ones((0, 2)), np.ones(0)),  # no rows
        (np.array([[np.nan, 1.0]]), np.ones(1)),
        (np.array([[1.0, 1.0]]), np.array([np.inf])),
        (np.array([[0.0, 0.0]]), np.array([-1.0])),  # zero normal
    ],
)
def test_bad_constraint_shapes(ref, kernel, G, c):
    with pytest.raises(ValueError):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(G, c))


# ----------------------------------------------------------------- per-step path input handling
# grid_step is the actor's hot path and does no validation of its own. The three tests below document
# what that lets through (see the report): they fail on the current implementation.
def test_grid_step_rejects_column_xi(model):
    """xi of shape (O, 1) is silently broadcast: grid_step returns an (O, O) array instead of (O,)."""
    with pytest.raises(ValueError):
        model.grid_step(3, np.zeros((2, 1)))


@pytest.mark.parametrize("which", ["model", "box_model"])
def test_grid_step_rejects_nan_xi(request, which):
    """A NaN action propagates silently into the commanded trajectory point."""
    m = request.getfixturevalue(which)
    with pytest.raises(ValueError):
        m.grid_step(3, np.array([np.nan, 0.0]))


def test_grid_step_negative_index_consistent(model, box_model):
    """n = -1 must mean the same thing with and without constraints (or be rejected by both). Today the
    unconstrained model returns the last grid point while the constrained one fails inside numpy: its
    constraint rows are sliced as ``_P[n*O:(n+1)*O]``, which is empty for n = -1."""
    xi = np.array([1.0, -1.0])
    outcomes = []
    for m in (model, box_model):
        try:
            eta = m.grid_step(-1, xi)
        except (IndexError, ValueError):
            outcomes.append("rejected")
        else:
            outcomes.append("last" if np.allclose(eta, m.grid_step(m.n_points - 1, xi), atol=1e-12) else "other")
    assert outcomes[0] == outcomes[1] and "other" not in outcomes, outcomes


def test_grid_step_wrong_length_xi_rejected(model, box_model):
    for m in (model, box_model):
        with pytest.raises(ValueError):
            m.grid_step(3, np.zeros(3))
        with pytest.raises((ValueError, IndexError)):
            m.grid_step(N_REF, np.zeros(2))
