"""Kernels for KMP.

A kernel is any callable ``k(S1, S2) -> K`` with ``S1`` of shape (n1, I), ``S2`` of shape (n2, I)
and ``K`` of shape (n1, n2), float64. :class:`RBF` is the one the paper uses (Section II-B).

Two RBF conventions exist in the KMP literature (``math.md`` §1):

* length-scale form (this class): ``k(a, b) = variance * exp(-||a - b||^2 / (2 * length_scale^2))``;
* precision form (the authors' ``lc-ns-kmp`` library): ``k(a, b) = exp(-l * ||a - b||^2)``.

They are the same kernel with ``length_scale = 1 / sqrt(2 l)`` and ``variance = 1``;
:meth:`RBF.from_precision` converts. The KMP code never assumes ``k(s, s) = 1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

Kernel = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class RBF:
    """Squared-exponential kernel ``variance * exp(-||a-b||^2 / (2 length_scale^2))``."""

    length_scale: float = 0.05
    variance: float = 1.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.length_scale) and self.length_scale > 0):
            raise ValueError(f"RBF length_scale must be finite and > 0, got {self.length_scale}")
        if not (np.isfinite(self.variance) and self.variance > 0):
            raise ValueError(f"RBF variance must be finite and > 0, got {self.variance}")

    @classmethod
    def from_precision(cls, precision: float) -> "RBF":
        """The ``lc-ns-kmp`` convention ``exp(-l ||a-b||^2)`` (l = ``precision``) expressed as a length scale.

        :param precision: l > 0.
        """
        if not (np.isfinite(precision) and precision > 0):
            raise ValueError(f"RBF precision must be finite and > 0, got {precision}")
        return cls(length_scale=float(1.0 / np.sqrt(2.0 * precision)), variance=1.0)

    @property
    def precision(self) -> float:
        """``l`` in the precision form ``exp(-l ||a-b||^2)``."""
        return float(1.0 / (2.0 * self.length_scale**2))

    def __call__(self, s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
        s1 = np.asarray(s1, dtype=np.float64)
        s2 = np.asarray(s2, dtype=np.float64)
        if s1.ndim != 2 or s2.ndim != 2 or s1.shape[1] != s2.shape[1]:
            raise ValueError(f"RBF expects (n1, I) and (n2, I) inputs, got {s1.shape} and {s2.shape}")
        d2 = np.sum(s1 * s1, axis=1)[:, None] + np.sum(s2 * s2, axis=1)[None, :] - 2.0 * s1 @ s2.T
        np.maximum(d2, 0.0, out=d2)
        return self.variance * np.exp(-0.5 * d2 / self.length_scale**2)

    def diag(self, s: np.ndarray) -> np.ndarray:
        """``k(s_i, s_i)`` for every row (constant for a stationary kernel)."""
        return np.full(np.asarray(s).shape[0], self.variance, dtype=np.float64)


def kernel_diag(kernel: Kernel, s: np.ndarray) -> np.ndarray:
    """``k(s_i, s_i)`` for each row of ``s`` (uses ``kernel.diag`` when available)."""
    diag = getattr(kernel, "diag", None)
    if callable(diag):
        return np.asarray(diag(s), dtype=np.float64)
    return np.array([kernel(row[None, :], row[None, :])[0, 0] for row in s], dtype=np.float64)


def evaluate_kernel(kernel: Kernel, s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """Call a user kernel and check that it returned a finite (n1, n2) float64 array."""
    out = np.asarray(kernel(s1, s2), dtype=np.float64)
    if out.shape != (s1.shape[0], s2.shape[0]):
        raise ValueError(
            f"kernel returned shape {out.shape}, expected {(s1.shape[0], s2.shape[0])} "
            "(a kernel must map (n1, I), (n2, I) -> (n1, n2))"
        )
    if not np.all(np.isfinite(out)):
        raise ValueError("kernel returned non-finite values")
    return out
