"""Input validation of LC-NS-KMP: the reference distribution, the hyperparameters and the linear constraints.

Constraints ``(G, c)`` mean ``G[n, f] @ eta(s_n) >= c[n, f]`` at every grid input; ``G`` is (F, O) (shared by
all points) or (N, F, O), ``c`` is (F,) or (N, F). Used by :class:`khgrl.common.kmp.lcnskmp.LCNSKMP`.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize

__all__ = [
    "InfeasibleConstraintsError",
    "as_2d",
    "check_reference",
    "check_hyperparameters",
    "normalise_constraints",
    "check_feasible",
]


def as_2d(name: str, x: np.ndarray, cols: int | None = None) -> np.ndarray:
    """``x`` as a finite float64 (n, cols) array; a 1-D array is taken as one column when ``cols == 1``.

    :param name: the argument's name, for the error message.
    :param x: the array.
    :param cols: required number of columns, or None for any.
    :raises ValueError: wrong shape or non-finite values.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1 and cols is not None and cols == 1:
        x = x[:, None]
    if x.ndim != 2 or (cols is not None and x.shape[1] != cols):
        want = f"(n, {cols})" if cols is not None else "(n, d)"
        raise ValueError(f"{name} must have shape {want}, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf")
    return x


def check_reference(
    s: np.ndarray, mu: np.ndarray, sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate the reference distribution.

    :param s: (N, I) reference inputs.
    :param mu: (N, O) reference means.
    :param sigma: (N, O, O) reference covariances.
    :return: float64 ``s``, ``mu`` and ``sigma`` (sigma symmetrised).
    :raises ValueError: wrong shapes, non-finite values, sigma not symmetric positive definite at some point.
    """
    s = as_2d("s", s)
    n = s.shape[0]
    mu = as_2d("mu", mu)
    if mu.shape[0] != n:
        raise ValueError(f"mu has {mu.shape[0]} rows but s has {n}")
    o = mu.shape[1]
    sig = np.asarray(sigma, dtype=np.float64)
    if sig.shape != (n, o, o):
        raise ValueError(f"sigma must have shape {(n, o, o)}, got {sig.shape}")
    if not np.all(np.isfinite(sig)):
        raise ValueError("sigma contains NaN or inf")
    if not np.allclose(sig, np.swapaxes(sig, 1, 2), rtol=1e-8, atol=1e-12):
        raise ValueError("sigma must be symmetric at every point")
    sig = 0.5 * (sig + np.swapaxes(sig, 1, 2))
    eig_min = np.linalg.eigvalsh(sig).min(axis=1)
    if np.any(eig_min <= 0.0):
        bad = int(np.argmin(eig_min))
        raise ValueError(
            f"sigma must be positive definite at every point (smallest eigenvalue {eig_min[bad]:.3g} at "
            f"point {bad}); add jitter to the reference covariances"
        )
    return s, mu, sig


def check_hyperparameters(lam: float, beta: float) -> None:
    """:raises ValueError: unless lambda and beta are finite and > 0."""
    for name, v in (("lam", lam), ("beta", beta)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0, got {v}")


class InfeasibleConstraintsError(ValueError):
    """The linear constraints admit no point at some grid input."""


def normalise_constraints(G: np.ndarray, c: np.ndarray, n: int, o: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate ``(G, c)`` and broadcast shared constraints to every grid point.

    :param G: (F, O) shared or (N, F, O) per-point constraint normals.
    :param c: (F,) or (N, F) bounds.
    :param n: N, grid points.
    :param o: O, output dimensions.
    :return: G (N, F, O) and c (N, F), float64 copies.
    :raises ValueError: wrong shapes, F = 0, non-finite values or a zero normal.
    """
    G = np.asarray(G, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    if G.ndim == 2:
        if G.shape[1] != o or c.shape != (G.shape[0],):
            raise ValueError(f"shared constraints need G (F, {o}) and c (F,), got {G.shape} and {c.shape}")
        G = np.broadcast_to(G, (n, *G.shape)).copy()
        c = np.broadcast_to(c, (n, c.shape[0])).copy()
    elif G.ndim == 3:
        if G.shape[0] != n or G.shape[2] != o or c.shape != G.shape[:2]:
            raise ValueError(
                f"per-point constraints need G ({n}, F, {o}) and c ({n}, F), got {G.shape} and {c.shape}"
            )
    else:
        raise ValueError(f"G must have shape (F, O) or (N, F, O), got {G.shape}")
    if G.shape[1] == 0:
        raise ValueError("constraints given with F = 0 rows; pass constraints=None instead")
    if not (np.all(np.isfinite(G)) and np.all(np.isfinite(c))):
        raise ValueError("constraints contain NaN or inf")
    if np.any(np.linalg.norm(G, axis=2) == 0.0):
        raise ValueError("constraint normals g must be non-zero")
    return G, c


def check_feasible(G: np.ndarray, c: np.ndarray) -> None:
    """Each grid point's polyhedron {eta : G_n eta >= c_n} must be non-empty (one LP per distinct set).

    :param G: (N, F, O) constraint normals.
    :param c: (N, F) bounds.
    :raises InfeasibleConstraintsError: naming the first grid point without a solution.
    """
    stacked = np.concatenate([G.reshape(G.shape[0], -1), c], axis=1)
    _, first = np.unique(stacked, axis=0, return_index=True)
    for idx in np.sort(first):
        res = scipy.optimize.linprog(
            np.zeros(G.shape[2]), A_ub=-G[idx], b_ub=-c[idx], bounds=[(None, None)] * G.shape[2], method="highs"
        )
        if res.status == 2:
            raise InfeasibleConstraintsError(
                f"constraints at grid point {idx} admit no solution: G={G[idx].tolist()} c={c[idx].tolist()}"
            )
