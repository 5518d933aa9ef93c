"""Gaussian-process regression with fixed hyperparameters: the regression behind the learned scale L
(paper Section III-C, math.md §5).

The kernel is a squared exponential plus white noise,

    k(x, x') = signal_var * exp(-|x - x'|^2 / (2 length_scale^2)) + noise_var * [x == x'],

and the posterior mean at query points X* is

    mu(X*) = k(X*, X) alpha,   alpha = (K + jitter I)^-1 y,   K = k(X, X),

with alpha from the Cholesky factor of K + jitter I (two triangular solves: K is never inverted). One factor
serves every output column, since they share their inputs.

The arithmetic is scikit-learn's ``GaussianProcessRegressor(kernel=signal_var * RBF(length_scale) +
WhiteKernel(noise_var), optimizer=None, alpha=jitter)`` operation for operation, so the means are the same to the
last bit (``tests/unit/test_gpr.py`` holds it to that). It is written out here because importing scikit-learn's
Gaussian processes costs an actor about 1.5 CPU-s at every start, and because fitting one factor for all outputs
does the work once where one regressor per output did it once per output (plus a log-likelihood nobody reads).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_solve, cholesky
from scipy.spatial.distance import cdist, pdist, squareform

__all__ = ["GPR"]


class GPR:
    """Posterior mean of a Gaussian process with a squared-exponential kernel and white noise (math.md §5).

    :param signal_var: the kernel's signal variance (its value at distance 0, noise aside)
    :param length_scale: the kernel's length scale, in units of the input
    :param noise_var: the white noise's variance, on the diagonal of K
    :param jitter: added to K's diagonal before the Cholesky factorisation (scikit-learn's ``alpha``)
    """

    def __init__(self, signal_var: float, length_scale: float, noise_var: float, jitter: float = 1e-10) -> None:
        self.signal_var = float(signal_var)
        self.length_scale = float(length_scale)
        self.noise_var = float(noise_var)
        self.jitter = float(jitter)
        self._x: np.ndarray | None = None
        self._alphas: list[np.ndarray] = []

    def _signal(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """signal_var * exp(-|a - b|^2 / (2 length_scale^2)), (len(a), len(b)); with ``b`` None, k(a, a)."""
        if b is None:
            rbf = squareform(np.exp(-0.5 * pdist(a / self.length_scale, metric="sqeuclidean")))
            np.fill_diagonal(rbf, 1)
        else:
            rbf = np.exp(-0.5 * cdist(a / self.length_scale, b / self.length_scale, metric="sqeuclidean"))
        return np.full(rbf.shape, self.signal_var) * rbf

    def fit(self, x: np.ndarray, y: np.ndarray) -> GPR:
        """Condition on inputs ``x`` (n, d) and targets ``y`` (n, m): alpha per column, from one Cholesky factor.

        :param x: training inputs, float64
        :param y: training targets, one regression per column
        :return: this regressor
        """
        x = np.array(x, dtype=np.float64, ndmin=2)
        y = np.asarray(y, dtype=np.float64).reshape(x.shape[0], -1)
        k = self._signal(x) + self.noise_var * np.eye(x.shape[0])
        k[np.diag_indices_from(k)] += self.jitter
        factor = (cholesky(k, lower=True, check_finite=False), True)
        self._alphas = [cho_solve(factor, np.ascontiguousarray(y[:, j]), check_finite=False) for j in range(y.shape[1])]
        self._x = x
        return self

    def predict(self, x: np.ndarray) -> np.ndarray:
        """The posterior mean at ``x`` (k, d): (k, m), one column per fitted target column.

        :param x: query inputs
        :return: mu(x)
        """
        if self._x is None:
            raise RuntimeError("GPR.predict before fit")
        k_trans = self._signal(np.array(x, dtype=np.float64, ndmin=2), self._x)
        return np.stack([k_trans @ alpha for alpha in self._alphas], axis=1)
