"""Via-point adaptation of the LC-NS-KMP: the mean made to pass through points read from the scene (issue 22).

The KMP paper adapts a learned trajectory to new via-points and end-points without new demonstrations (Huang et al.,
"Kernelized movement primitives", IJRR 2019, "trajectory modulation"): each desired point (s_bar, mu_bar,
Sigma_bar) is added to the reference database D = {(s_n, mu_hat_n, Sigma_hat_n)}, where an input that coincides with
a reference input *replaces* that reference point (two points at one input would contradict each other), and the
KMP is solved again on the extended database. A small Sigma_bar makes the mean pass (nearly) through mu_bar.

Here the desired points are snapped to the nearest input of the model's reference grid, so they always replace a
reference point: the actor only visits grid inputs (s_t = t / (N - 1)), the grid keeps its N points, and every
per-step table (math.md §6) keeps its meaning. Everything downstream follows the adapted database, because it is
an ordinary LC-NS-KMP solved on it (math.md §3, with A = (K + gamma Sigma)^-1 of the adapted Sigma):

* the mean eta0_n = [K A mu]_n (eq. 4 with xi = 0) passes within ~gamma |Sigma_bar (A mu)_n| of mu_bar;
* the hard constraints (the workspace box and the task's G P >= c) are imposed at every grid input as before
  (the dual of eq. 3); a via-point outside them is reached only as far as they allow;
* the soft null-space projector N(s_n) <= beta Sigma_n (eq. 5, math.md §4) narrows to ~beta Sigma_bar at the via
  point: the band and the RL's reach shrink there, and the KGRL mapping (eq. 5) and the human's inverse (eq. 6)
  are taken about the adapted mean.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from khgrl.common.kmp.lcnskmp import LCNSKMP

__all__ = ["adapt_model", "snap_via_points", "Snapped"]


@dataclass(frozen=True)
class Snapped:
    """A via-point on the model's grid: the grid step it replaces, its position mu_bar and covariance Sigma_bar."""

    step: int
    position: np.ndarray  # (O,)
    sigma: np.ndarray  # (O, O)


def snap_via_points(model: LCNSKMP, via: Sequence[Any]) -> list[Snapped]:
    """Check via-points and snap each to the nearest grid input of ``model`` (I = 1: the phase).

    :param model: the LC-NS-KMP of the demonstrations.
    :param via: objects with ``phase`` (in [0, 1]), ``position`` (O,) and ``precision`` (> 0, 1 / variance):
        :class:`khgrl.common.tasks.scene.ViaPoint`.
    :raises ValueError: a phase outside [0, 1], a position of the wrong size or not finite, a precision <= 0, or two
        via-points on one grid step.
    """
    if model.in_dim != 1:
        raise ValueError(f"via-points need a phase-input KMP (I = 1), this one has I = {model.in_dim}")
    grid = model.s[:, 0]
    out: list[Snapped] = []
    for k, v in enumerate(via):
        phase = float(v.phase)
        pos = np.asarray(v.position, dtype=np.float64).reshape(-1)
        prec = float(v.precision)
        if not (np.isfinite(phase) and 0.0 <= phase <= 1.0):
            raise ValueError(f"via-point {k}: phase must be in [0, 1], got {v.phase!r}")
        if pos.shape != (model.out_dim,) or not np.all(np.isfinite(pos)):
            raise ValueError(f"via-point {k}: position must be {model.out_dim} finite values, got {v.position!r}")
        if not (np.isfinite(prec) and prec > 0.0):
            raise ValueError(f"via-point {k}: precision must be > 0, got {v.precision!r}")
        step = int(np.argmin(np.abs(grid - phase)))
        if any(s.step == step for s in out):
            raise ValueError(f"via-point {k}: phase {phase:g} falls on grid step {step} like an earlier via-point "
                             f"(the grid's spacing is {1.0 / max(len(grid) - 1, 1):.3g})")
        out.append(Snapped(step, pos, np.eye(model.out_dim) / prec))
    return out


def adapt_model(model: LCNSKMP, via: Sequence[Any]) -> LCNSKMP:
    """The LC-NS-KMP refitted with ``via`` added to its reference database (see the module docstring).

    The reference point at each via-point's grid step is replaced by (mu_bar, Sigma_bar = I / precision); the
    kernel, lambda, beta and hard constraints are the model's. ``model`` itself is not changed; no via-points give
    ``model`` back.

    :param model: the LC-NS-KMP of the demonstrations.
    :param via: via-points (:class:`khgrl.common.tasks.scene.ViaPoint`).
    :raises ValueError: see :func:`snap_via_points`.
    """
    snapped = snap_via_points(model, via)
    if not snapped:
        return model
    mu, sigma = model.mu.copy(), model.sigma.copy()
    for s in snapped:
        mu[s.step], sigma[s.step] = s.position, s.sigma
    return LCNSKMP(model.s, mu, sigma, lam=model.lam, beta=model.beta, kernel=model.kernel,
                   constraints=model.constraints)
