"""RBF conventions and user-kernel validation (math.md §1)."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.kmp.kernels import RBF, evaluate_kernel, kernel_diag
from khgrl.common.kmp.lcnskmp import LCNSKMP

from kmp_problems import BETA, LAM


def _sqdist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2)


@pytest.fixture()
def points() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    return rng.uniform(-1, 1, size=(7, 3)), rng.uniform(-1, 1, size=(5, 3))


def test_length_scale_form(points):
    a, b = points
    k = RBF(length_scale=0.3, variance=2.5)
    expected = 2.5 * np.exp(-_sqdist(a, b) / (2 * 0.3**2))
    np.testing.assert_allclose(k(a, b), expected, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("prec", [0.5, 2.0, 50.0, 1234.5])
def test_from_precision_is_exp_minus_l_d2(points, prec):
    a, b = points
    k = RBF.from_precision(prec)
    np.testing.assert_allclose(k(a, b), np.exp(-prec * _sqdist(a, b)), rtol=1e-12, atol=1e-300)
    assert k.variance == 1.0
    np.testing.assert_allclose(k(a, a).diagonal(), 1.0, rtol=0, atol=1e-15)


@pytest.mark.parametrize("prec", [1e-3, 0.5, 2.0, 50.0, 1e4])
def test_precision_round_trip(prec):
    assert RBF.from_precision(prec).precision == pytest.approx(prec, rel=1e-14)


@pytest.mark.parametrize("length_scale", [1e-3, 0.05, 0.7, 30.0])
def test_length_scale_round_trip(length_scale):
    k = RBF(length_scale=length_scale)
    assert RBF.from_precision(k.precision).length_scale == pytest.approx(length_scale, rel=1e-14)
    # the precision form of the same kernel gives the same Gram matrix
    s = np.linspace(0, 1, 9)[:, None]
    np.testing.assert_allclose(k(s, s), np.exp(-k.precision * _sqdist(s, s)), rtol=1e-12)


def test_rbf_gram_symmetric_and_diag(points):
    a, _ = points
    k = RBF(length_scale=0.4, variance=3.0)
    g = k(a, a)
    np.testing.assert_array_equal(g, g.T)
    np.testing.assert_allclose(np.diag(g), 3.0, rtol=1e-15)
    np.testing.assert_allclose(k.diag(a), 3.0)
    assert np.linalg.eigvalsh(g).min() > 0


@pytest.mark.parametrize("bad", [dict(length_scale=0.0), dict(length_scale=-1.0), dict(length_scale=np.nan),
                                 dict(variance=0.0), dict(variance=np.inf)])
def test_rbf_bad_parameters(bad):
    with pytest.raises(ValueError):
        RBF(**bad)


@pytest.mark.parametrize("prec", [0.0, -2.0, np.nan, np.inf])
def test_from_precision_bad(prec):
    with pytest.raises(ValueError):
        RBF.from_precision(prec)


def test_rbf_bad_input_shapes():
    k = RBF()
    with pytest.raises(ValueError):
        k(np.zeros(3), np.zeros((2, 1)))
    with pytest.raises(ValueError):
        k(np.zeros((3, 2)), np.zeros((2, 1)))


def test_kernel_diag_without_diag_method():
    k = RBF(length_scale=0.2, variance=1.7)
    s = np.linspace(0, 1, 6)[:, None]
    np.testing.assert_allclose(kernel_diag(lambda a, b: k(a, b), s), 1.7)


def test_custom_callable_kernel_matches_rbf(ref):
    """A plain function (no ``diag``, no RBF type) is accepted and gives the same model as RBF."""
    rbf = RBF(length_scale=0.1, variance=1.3)

    def plain(a, b):
        d2 = ((np.asarray(a)[:, None, :] - np.asarray(b)[None, :, :]) ** 2).sum(axis=2)
        return 1.3 * np.exp(-d2 / (2 * 0.1**2))

    m_rbf = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=rbf)
    m_fn = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=plain)
    q = np.linspace(0, 1, 23)[:, None]
    xi = np.array([1.5, -0.7])
    np.testing.assert_allclose(m_fn.predict(q, xi, [0.37]), m_rbf.predict(q, xi, [0.37]), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(m_fn.projector(q), m_rbf.projector(q), rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(m_fn.grid_projector, m_rbf.grid_projector, rtol=1e-9, atol=1e-14)


def test_non_stationary_callable_kernel_used(ref):
    """A non-RBF kernel (linear + RBF) really changes the prediction: the callable is used, not ignored."""
    rbf = RBF(length_scale=0.1)

    def lin_plus_rbf(a, b):
        return rbf(a, b) + 4.0 * np.asarray(a) @ np.asarray(b).T

    m_rbf = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=rbf)
    m_lin = LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=lin_plus_rbf)
    q = np.linspace(0, 1, 11)[:, None]
    assert np.abs(m_lin.predict(q) - m_rbf.predict(q)).max() > 1e-3
    # k(s, s) != 1 here: the projector is still bounded by beta / gamma and positive definite
    eig = np.linalg.eigvalsh(m_lin.projector(q))
    assert eig.min() > 0 and eig.max() <= BETA / (LAM + BETA) * (1 + 1e-12)


def test_bad_kernel_wrong_shape(ref):
    with pytest.raises(ValueError, match="shape"):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=lambda a, b: np.ones((a.shape[0], 1)))
    with pytest.raises(ValueError, match="shape"):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=lambda a, b: RBF()(a, b).T[:-1])


def test_bad_kernel_nan(ref):
    def nan_kernel(a, b):
        k = RBF()(a, b)
        k[0, -1] = np.nan
        return k

    with pytest.raises(ValueError, match="non-finite"):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=nan_kernel)


def test_bad_kernel_non_positive_diagonal(ref):
    with pytest.raises(ValueError):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=lambda a, b: -RBF()(a, b))


def test_evaluate_kernel_checks():
    s = np.zeros((3, 1))
    with pytest.raises(ValueError):
        evaluate_kernel(lambda a, b: np.zeros((3, 4)), s, s)
    with pytest.raises(ValueError):
        evaluate_kernel(lambda a, b: np.full((3, 3), np.inf), s, s)
    out = evaluate_kernel(lambda a, b: np.ones((3, 3), dtype=np.float32), s, s)
    assert out.dtype == np.float64
