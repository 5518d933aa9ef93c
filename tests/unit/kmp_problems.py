"""Shared small LC-NS-KMP problems for the math-core tests (math.md §7).

Everything here is deterministic and small (N <= 60, O = 2) so that the whole suite stays fast and
the dense reference computations (numpy inverses, cvxpy) are cheap and well conditioned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from khgrl.common.kmp.kernels import RBF
from khgrl.common.kmp.lcnskmp import LCNSKMP

# Hyperparameters used throughout (gamma = 2.5).
LAM = 0.5
BETA = 2.0
# Precision-form RBF exp(-l ||d||^2) with l = 50  (length scale 0.1 in the other convention).
PRECISION = 50.0


@dataclass(frozen=True)
class Reference:
    """A GMR-like reference distribution on a time grid: s (N, 1), mu (N, O), sigma (N, O, O)."""

    s: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray

    @property
    def n(self) -> int:
        return self.s.shape[0]

    @property
    def o(self) -> int:
        return self.mu.shape[1]


def make_reference(n: int = 40, seed: int = 0) -> Reference:
    """Smooth 2-D mean (a loop) with full, point-dependent covariances: large in the middle of the
    trajectory (demos disagree), small at both ends (demos agree), random orientation."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n)
    mu = np.c_[np.sin(2 * np.pi * t), 0.5 * np.cos(2 * np.pi * t)]
    scale = 1e-3 + 0.05 * np.sin(np.pi * t) ** 2
    sigma = np.empty((n, 2, 2))
    for k in range(n):
        a = rng.normal(size=(2, 2))
        sigma[k] = scale[k] * (a @ a.T / 2.0 + 0.3 * np.eye(2))
    return Reference(s=t[:, None], mu=mu, sigma=sigma)


# Box |x| <= 0.6, |y| <= 0.35 as G eta >= c: it cuts both output dims of the loop above, so the
# constraints are active already for xi = 0.
BOX_G = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
BOX_C = np.array([-0.6, -0.6, -0.35, -0.35])
# A far-away box: never active for moderate xi.
LOOSE_C = np.array([-50.0, -50.0, -50.0, -50.0])


@pytest.fixture(scope="session")
def ref() -> Reference:
    return make_reference(40, seed=0)


@pytest.fixture(scope="session")
def kernel() -> RBF:
    return RBF.from_precision(PRECISION)


@pytest.fixture(scope="session")
def model(ref: Reference, kernel: RBF) -> LCNSKMP:
    """Unconstrained model."""
    return LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel)


@pytest.fixture(scope="session")
def box_model(ref: Reference, kernel: RBF) -> LCNSKMP:
    """Model with the box constraints, active already at xi = 0. Session scope: ``grid_step`` keeps the
    previous step's active set as a warm start, and sharing it across tests exercises exactly that."""
    return LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(BOX_G, BOX_C))


@pytest.fixture(scope="session")
def loose_model(ref: Reference, kernel: RBF) -> LCNSKMP:
    """Model with constraints that are never active (alpha = 0 by the KKT shortcut)."""
    return LCNSKMP(ref.s, ref.mu, ref.sigma, lam=LAM, beta=BETA, kernel=kernel, constraints=(BOX_G, LOOSE_C))


def dense_A(ref: Reference, kmat: np.ndarray, gamma: float) -> np.ndarray:
    """(K + gamma Sigma)^-1 by a plain numpy inverse: an independent reference on small problems."""
    import scipy.linalg

    K = np.kron(kmat, np.eye(ref.o))
    Sigma = scipy.linalg.block_diag(*ref.sigma)
    return np.linalg.inv(K + gamma * Sigma)
