"""Reference trajectory distribution from demonstrations: GMM + GMR (paper Section II-A, math.md §2).

The GMM is scikit-learn's :class:`~sklearn.mixture.GaussianMixture` with full covariances fitted on the
joint (input, output) points; GMR conditions every component on the input and moment-matches the
mixture, as in every reference KMP implementation. scikit-learn is imported when a GMM is fitted, not with this
module, and a fit of the same points is read from a cache (:mod:`khgrl.common.kmp.gmm_cache`): a process that only
loads a task, or fits demonstrations fitted before, does not pay for it (~1.5 s).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from khgrl.common.kmp.gmm_cache import FittedGMM, gmm_key, load_gmm, store_gmm

if TYPE_CHECKING:
    from sklearn.mixture import GaussianMixture


@dataclass(frozen=True)
class ReferenceDistribution:
    """GMR output on a grid: inputs ``s`` (N, I), means ``mu`` (N, O), covariances ``sigma`` (N, O, O)."""

    s: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray


def _check_demos(demos: np.ndarray) -> np.ndarray:
    demos = np.asarray(demos, dtype=np.float64)
    if demos.ndim != 3:
        raise ValueError(f"demonstrations must have shape (M, N, O), got {demos.shape}")
    m, n, o = demos.shape
    if m < 1 or n < 2 or o < 1:
        raise ValueError(f"need at least 1 demonstration of >= 2 points with >= 1 output, got {demos.shape}")
    if not np.all(np.isfinite(demos)):
        raise ValueError("demonstrations contain NaN or inf")
    return demos


def time_inputs(n_points: int) -> np.ndarray:
    """Normalised time grid ``s_n = n / (N - 1)`` in [0, 1], shape (N, 1)."""
    return np.linspace(0.0, 1.0, n_points, dtype=np.float64)[:, None]


def fit_gmm(
    demos: np.ndarray, n_components: int = 8, *, seed: int = 0, reg_covar: float = 1e-6
) -> GaussianMixture | FittedGMM:
    """Fit a full-covariance GMM on the joint (s, eta) points of time-indexed demonstrations.

    ``demos`` has shape (M, N, O); each demonstration's time is normalised to [0, 1]. The fit is scikit-learn's, or
    the same fit read back from the cache (:mod:`khgrl.common.kmp.gmm_cache`): either has ``weights_``, ``means_``
    and ``covariances_``.
    """
    demos = _check_demos(demos)
    m, n, o = demos.shape
    s = np.broadcast_to(time_inputs(n)[None], (m, n, 1))
    data = np.concatenate([s, demos], axis=2).reshape(m * n, 1 + o)
    if n_components < 1 or n_components > data.shape[0]:
        raise ValueError(f"n_components must be in [1, {data.shape[0]}], got {n_components}")
    key = gmm_key(data, n_components, seed, reg_covar)
    cached = load_gmm(key, n_components, 1 + o)
    if cached is not None:
        return cached
    from sklearn.mixture import GaussianMixture

    gmm = GaussianMixture(
        n_components=n_components, covariance_type="full", random_state=seed, reg_covar=reg_covar, n_init=1
    )
    gmm.fit(data)
    store_gmm(key, FittedGMM(gmm.weights_, gmm.means_, gmm.covariances_))
    return gmm


def gmr(
    weights: np.ndarray, means: np.ndarray, covariances: np.ndarray, s_query: np.ndarray, n_inputs: int
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian mixture regression of the last ``D - n_inputs`` dims on the first ``n_inputs``.

    Args:
        weights: (C,) component priors p_c.
        means: (C, D) joint means.
        covariances: (C, D, D) joint full covariances.
        s_query: (Q, I) inputs.
        n_inputs: I.

    Returns:
        mu (Q, O) and sigma (Q, O, O), the moment-matched conditional mixture:
        mu = sum_c h_c m_c,  sigma = sum_c h_c (S_c + m_c m_c^T) - mu mu^T.
    """
    weights = np.asarray(weights, dtype=np.float64)
    means = np.asarray(means, dtype=np.float64)
    covariances = np.asarray(covariances, dtype=np.float64)
    s_query = np.atleast_2d(np.asarray(s_query, dtype=np.float64))
    i = n_inputs
    if s_query.shape[1] != i:
        raise ValueError(f"s_query must have {i} columns, got shape {s_query.shape}")
    c_count = weights.shape[0]
    mu_s, mu_e = means[:, :i], means[:, i:]
    s_ss = covariances[:, :i, :i]
    s_es = covariances[:, i:, :i]
    s_ee = covariances[:, i:, i:]

    # log responsibilities log p_c + log N(s | mu_s_c, S_ss_c), via Cholesky (no explicit inverse).
    chol = np.linalg.cholesky(s_ss)  # (C, I, I)
    diff = s_query[None, :, :] - mu_s[:, None, :]  # (C, Q, I)
    z = np.stack([np.linalg.solve(chol[c], diff[c].T).T for c in range(c_count)])  # (C, Q, I)
    logdet = 2.0 * np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)  # (C,)
    log_p = np.log(weights)[:, None] - 0.5 * (np.sum(z * z, axis=2) + logdet[:, None] + i * np.log(2 * np.pi))
    log_p -= log_p.max(axis=0, keepdims=True)
    h = np.exp(log_p)
    h /= h.sum(axis=0, keepdims=True)  # (C, Q)

    # Conditional means m_c(s) = mu_e + S_es S_ss^{-1} (s - mu_s) and covariances S_c = S_ee - S_es S_ss^{-1} S_se.
    gain = np.stack([np.linalg.solve(s_ss[c], s_es[c].T).T for c in range(c_count)])  # (C, O, I)
    m_c = mu_e[:, None, :] + np.einsum("coi,cqi->cqo", gain, diff)  # (C, Q, O)
    cond_cov = s_ee - np.einsum("coi,cpi->cop", gain, s_es)  # (C, O, O)
    mu = np.einsum("cq,cqo->qo", h, m_c)
    second = np.einsum("cq,cop->qop", h, cond_cov) + np.einsum("cq,cqo,cqp->qop", h, m_c, m_c)
    sigma = second - np.einsum("qo,qp->qop", mu, mu)
    sigma = 0.5 * (sigma + np.swapaxes(sigma, 1, 2))
    return mu, sigma


def reference_distribution(
    demos: np.ndarray,
    n_points: int | None = None,
    n_components: int = 8,
    *,
    seed: int = 0,
    jitter: float = 1e-6,
) -> ReferenceDistribution:
    """GMM + GMR reference trajectory distribution on an N-point normalised time grid.

    ``jitter`` is added to every covariance's diagonal so that Sigma is strictly positive definite
    (math.md §1 recommends 1e-8 ... 1e-6).
    """
    demos = _check_demos(demos)
    n = demos.shape[1] if n_points is None else int(n_points)
    gmm = fit_gmm(demos, n_components, seed=seed)
    s = time_inputs(n)
    mu, sigma = gmr(gmm.weights_, gmm.means_, gmm.covariances_, s, n_inputs=1)
    sigma = sigma + jitter * np.eye(sigma.shape[1])[None]
    return ReferenceDistribution(s=s, mu=mu, sigma=sigma)
