"""The KGRL action mapping (eq. 5) and the KhGRL inverse path (eq. 6, Section III-B/C).

What the actor calls every control step, at time index t on the model's grid (s* = s_hat = s_t):

* :meth:`KGRLMapping.act` -- policy action a in [-1, 1]^O  ->  xi = L_t (.) a (*unscale*)  ->
  P_t = LC-NS-KMP prediction with hard constraints (``LCNSKMP.grid_step``);
* :meth:`KGRLMapping.intervene` -- human's desired position P_h  ->  xi_h = N_t^-1 (P_h - eta0_t) (eq. 6,
  alpha = 0)  ->  a_h = xi_h (/) L_t (*scale*), clipped to [-1, 1] with the clip counted. The robot is
  sent to P_h itself, the replay buffer gets a_h, and the transition is marked intervened.

Names follow the paper: ``unscale`` (a -> xi) and ``scale`` (xi -> a).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from khgrl.common.kmp.lcnskmp import LCNSKMP
from khgrl.common.kmp.scale import ScaleModel

__all__ = ["KGRLMapping", "Intervention", "unscale", "scale"]


def unscale(a: np.ndarray, L: np.ndarray) -> np.ndarray:
    """KGRL: xi = L (.) a (Section III-C)."""
    return L * a


def scale(xi: np.ndarray, L: np.ndarray) -> np.ndarray:
    """KhGRL: a = xi (/) L (Section III-C)."""
    return xi / L


@dataclass(frozen=True)
class Intervention:
    """The action a human correction maps to at one step."""

    action: np.ndarray  # a_h, clipped to [-1, 1]
    xi: np.ndarray  # xi_h, unclipped null-space action (eq. 6)
    raw_action: np.ndarray  # xi_h / L_t before clipping
    clipped: bool  # |raw_action| > 1 in some dimension: the stored action no longer reproduces P_h


class KGRLMapping:
    """Action <-> desired position on the LC-NS-KMP grid, with the exploration scale L.

    Args:
        model: the LC-NS-KMP (with the hard constraints, e.g. the workspace box).
        scale_model: L(x); :meth:`refresh_scale` tabulates it on the grid (phase input) after each update.
    """

    def __init__(self, model: LCNSKMP, scale_model: ScaleModel) -> None:
        if scale_model.dim != model.out_dim:
            raise ValueError(f"scale model has {scale_model.dim} dims, the KMP has {model.out_dim} outputs")
        self.model = model
        self.scale_model = scale_model
        self.phases = model.s[:, 0].copy()
        self.horizon = model.n_points
        self._table: np.ndarray | None = None
        self.refresh_scale()

    def use_model(self, model: LCNSKMP) -> None:
        """Drive with ``model`` from now on: the same grid and outputs, another reference database (a KMP adapted
        to this episode's via-points, :func:`khgrl.common.kmp.adapt.adapt_model`). L is tabulated over the phase
        and stays as it is."""
        if model.out_dim != self.model.out_dim or not np.array_equal(model.s, self.model.s):
            raise ValueError("use_model needs a model on the same grid with the same outputs")
        self.model = model

    def refresh_scale(self) -> None:
        """Re-tabulate L on the grid (call after the scale model changed)."""
        if self.scale_model.config.input == "phase":
            self._table = self.scale_model.table(self.phases)
        else:
            self._table = None

    @property
    def scale_table(self) -> np.ndarray | None:
        """(N, O) L on the grid (phase-input scale models), None for position input."""
        return self._table

    def scale_at(self, t: int, position: np.ndarray | None = None) -> np.ndarray:
        """L_t, the exploration scale in force at step t (O,)."""
        if self._table is not None:
            return self._table[t]
        return self.scale_model(position=position)

    def update_scale(self, xi_h: np.ndarray, phases: np.ndarray, positions: np.ndarray | None = None) -> None:
        """Refit L from one intervention's xi_h (k, O) at its phases (k,) / positions (k, 2), then re-tabulate."""
        self.scale_model.update(xi_h, phase=phases, position=positions)
        self.refresh_scale()

    def mean(self, t: int) -> np.ndarray:
        """eta0_t, the unconstrained KMP mean at step t."""
        return self.model.grid_mean[t]

    def act(self, t: int, a: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eq. (5): a -> xi = L (.) a -> P_t. Returns (P_t, xi)."""
        xi = unscale(np.asarray(a, dtype=np.float64), L)
        return self.model.grid_step(t, xi), xi

    def intervene(self, t: int, p_h: np.ndarray, L: np.ndarray) -> Intervention:
        """Eq. (6) then scale: P_h -> xi_h -> a_h = clip(xi_h (/) L_t, -1, 1).

        Eq. (6) assumes alpha = 0. If the hard constraints are active for that xi_h (its trajectory violates
        them somewhere on the grid), math.md §4 accounts for the constraint term: xi_h is then the solution of
        the constrained forward map = P_h (``LCNSKMP.grid_invert_constrained``).
        """
        xi = self.model.grid_invert_constrained(t, p_h)
        raw = scale(xi, L)
        clipped = bool(np.any(np.abs(raw) > 1.0))
        return Intervention(action=np.clip(raw, -1.0, 1.0), xi=xi, raw_action=raw, clipped=clipped)

    def band(self, L: np.ndarray | None = None) -> np.ndarray:
        """(N, 2, O) per grid point [low, high] of the unconstrained P reachable with |a| <= 1 under L
        (axis-aligned bound of eta0 + N (L (.) a)): what a viewer draws as the exploration band."""
        L = self._table if L is None else np.broadcast_to(L, (self.horizon, self.model.out_dim))
        if L is None:
            raise ValueError("band() needs an explicit L for a position-input scale model")
        half = np.einsum("nij,nj->ni", np.abs(self.model.grid_projector), L)
        mean = self.model.grid_mean
        return np.stack([mean - half, mean + half], axis=1)
