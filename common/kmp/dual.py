"""The dual QP of LC-NS-KMP's linear constraints: its fixed tables and the Gbar products (math.md §3, §6).

Constraints (validated by ``common/kmp/inputs.py``) are ``G`` (N, F, O) and ``c`` (N, F): ``G[n, f] @ eta(s_n)
>= c[n, f]``. ``Gbar`` is the block-diagonal (N*O, N*F) matrix of the per-point ``G[n].T``; vectors are
point-major. Used by :class:`khgrl.common.kmp.lcnskmp.LCNSKMP`.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "dual_tables",
    "gbar",
    "gbar_t",
    "least_distance_factor",
]


def gbar_t(G: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Gbar^T v for a point-major (N*O,) vector -> (N*F,).

    :param G: (N, F, O) constraint normals.
    :param v: (N*O,) point-major vector.
    """
    n, _, o = G.shape
    return np.einsum("nfo,no->nf", G, v.reshape(n, o)).reshape(-1)


def gbar(G: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Gbar alpha for (N*F,) -> point-major (N*O,).

    :param G: (N, F, O) constraint normals.
    :param alpha: (N*F,) multipliers.
    """
    return np.einsum("nfo,nf->no", G, alpha.reshape(G.shape[0], -1)).reshape(-1)


def dual_tables(
    M: np.ndarray, G: np.ndarray, c: np.ndarray, eta0: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The dual QP's fixed tables (eq. 3, corrected; math.md §3, §6).

    :param M: (N*O, N*O) ``K A Sigma``, symmetric PSD.
    :param G: (N, F, O) constraint normals.
    :param c: (N, F) bounds.
    :param eta0: (N, O) unconstrained grid mean.
    :return: ``P = M Gbar`` (N*O, N*F): the dual's linear term moves by (beta / k_nn) P[n-block]^T xi per
        step; ``Q = Gbar^T M Gbar`` (N*F, N*F), the dual's Hessian; ``q0 = Gbar^T eta0 - c`` (N*F,), the
        slack of the mean.
    """
    n, f, o = G.shape
    M4 = M.reshape(n, o, n, o)
    P = np.einsum("aibj,bfj->aibf", M4, G, optimize=True).reshape(n * o, n * f)
    Q = np.einsum("afi,aibg->afbg", G, P.reshape(n, o, n, f), optimize=True).reshape(n * f, n * f)
    Q = 0.5 * (Q + Q.T)
    q0 = gbar_t(G, eta0.reshape(-1)) - c.reshape(-1)
    return P, Q, q0


def least_distance_factor(M: np.ndarray, G: np.ndarray) -> np.ndarray:
    """H = Gbar^T R with M = R R^T (R from the eigen-decomposition of M, near-zero modes dropped): the
    least-distance form of the dual, for the interior-point fallback.

    :param M: (N*O, N*O) ``K A Sigma``.
    :param G: (N, F, O) constraint normals.
    :return: (N*F, r) factor.
    """
    n, f, o = G.shape
    evals, evecs = np.linalg.eigh(M)
    keep = evals > 1e-14 * evals[-1]
    R3 = (evecs[:, keep] * np.sqrt(evals[keep])).reshape(n, o, -1)
    return np.einsum("nfo,nor->nfr", G, R3).reshape(n * f, -1)
