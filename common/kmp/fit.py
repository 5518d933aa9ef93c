"""From demonstrations to an LC-NS-KMP model, with every hyperparameter in one config.

The model's code (GMM/GMR, the LC-NS-KMP and scipy behind them) is imported by :func:`fit_model`, not with this
module: a task's definition names a :class:`KMPConfig`, and a process that only loads tasks (a human-input client)
starts without the numerical stack (~1 s less).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from khgrl.common.kmp.gmr import ReferenceDistribution
    from khgrl.common.kmp.lcnskmp import LCNSKMP

__all__ = ["KMPConfig", "fit_model", "box_constraints"]


@dataclass(frozen=True)
class KMPConfig:
    """Hyperparameters of the reference distribution (GMM/GMR) and the LC-NS-KMP.

    ``length_scale`` is the RBF length scale in normalised time (k = exp(-ds^2 / (2 l^2)), see
    :class:`khgrl.common.kmp.kernels.RBF`).
    """

    lam: float = 1.0
    beta: float = 10.0
    length_scale: float = 0.02
    n_components: int = 10
    jitter: float = 1e-6
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def box_constraints(low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shared constraints ``low <= eta <= high`` as ``(G (2 O, O), c (2 O,))`` with ``G eta >= c``."""
    low = np.asarray(low, dtype=np.float64)
    high = np.asarray(high, dtype=np.float64)
    if low.shape != high.shape or low.ndim != 1 or np.any(low >= high):
        raise ValueError(f"box needs 1-D low < high of one shape, got {low} and {high}")
    eye = np.eye(low.size)
    return np.concatenate([eye, -eye]), np.concatenate([low, -high])


def fit_model(
    demos: np.ndarray, config: KMPConfig = KMPConfig(), constraints: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[LCNSKMP, ReferenceDistribution]:
    """GMM + GMR on the demonstrations' own N-point time grid, then the LC-NS-KMP on that grid."""
    from khgrl.common.kmp.gmr import reference_distribution
    from khgrl.common.kmp.kernels import RBF
    from khgrl.common.kmp.lcnskmp import LCNSKMP

    ref = reference_distribution(demos, n_components=config.n_components, seed=config.seed, jitter=config.jitter)
    model = LCNSKMP(
        ref.s,
        ref.mu,
        ref.sigma,
        lam=config.lam,
        beta=config.beta,
        kernel=RBF(length_scale=config.length_scale),
        constraints=constraints,
    )
    return model, ref
