"""The learned exploration scale L (paper Section III-C, math.md §5).

KGRL unscales the policy action a in [-1, 1]^O into the null-space action xi = L (.) a. KhGRL learns L
from the human: after each intervention, a Gaussian-process regression (:class:`~khgrl.common.kmp.gpr.GPR`) maps
the task region -- the KMP input s by default, the robot position as an option -- to the per-dimension magnitude
that covers the human's xi_h, with the default L as prior mean. The regression runs on log L, so L stays
positive and its prior is exactly the default away from the data:

    log L_d(x) = log L0_d + GP_d(x),   GP_d fitted to  log(max(|xi_h,d| * margin, min_scale)) - log L0_d.

A KGRL run simply never calls :meth:`ScaleModel.update` and keeps L = L0.

The model is plain data (:meth:`to_dict` / :meth:`from_dict`: numbers and lists only), so the actor can
publish it as msgpack; refitting is deterministic (fixed kernel hyperparameters, no optimiser restarts).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from khgrl.common.kmp.gpr import GPR

__all__ = ["ScaleConfig", "ScaleModel"]


@dataclass(frozen=True)
class ScaleConfig:
    """GPR settings. ``length_scale`` is in units of the regression input (phase s or workspace units)."""

    input: str = "phase"  # "phase" (KMP input s) or "position" (robot position)
    length_scale: float = 0.04
    signal_var: float = 4.0  # prior variance of log L around log L0
    noise_var: float = 0.05
    margin: float = 1.25  # L covers |xi_h| with this margin, so the human's action maps to |a| <= 0.8
    min_scale: float = 1.0
    max_points: int = 400  # data kept for the GP (binned on the input), bounds refit cost

    def __post_init__(self) -> None:
        if self.input not in ("phase", "position"):
            raise ValueError(f"scale input must be 'phase' or 'position', got {self.input!r}")
        for name in ("length_scale", "signal_var", "noise_var", "margin", "min_scale"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ScaleConfig.{name} must be > 0, got {v}")


class ScaleModel:
    """Region-dependent exploration scale L(x) >= min_scale, per action dimension.

    Args:
        default: L0, the default scale per dimension (prior mean), shape (O,) or a scalar with ``dim``.
        dim: O, when ``default`` is a scalar.
        config: GPR settings.
    """

    def __init__(self, default, dim: int | None = None, config: ScaleConfig = ScaleConfig()) -> None:
        default = np.atleast_1d(np.asarray(default, dtype=np.float64))
        if default.size == 1 and dim is not None:
            default = np.full(dim, float(default[0]))
        if default.ndim != 1 or not np.all(np.isfinite(default)) or np.any(default <= 0):
            raise ValueError(f"default scale must be positive and finite, got {default}")
        self.default = default
        self.config = config
        self._x = np.zeros((0, 1 if config.input == "phase" else 2))
        self._y = np.zeros((0, default.size))  # log targets minus log default
        self._gp: GPR | None = None  # once fitted: one regression per output, on shared inputs
        self.n_updates = 0

    @property
    def dim(self) -> int:
        return self.default.size

    @property
    def in_dim(self) -> int:
        return self._x.shape[1]

    @property
    def n_points(self) -> int:
        return self._x.shape[0]

    def _features(self, phase, position) -> np.ndarray:
        if self.config.input == "phase":
            x = np.asarray(phase, dtype=np.float64).reshape(-1, 1)
        else:
            if position is None:
                raise ValueError("this scale model regresses on position: pass position")
            x = np.asarray(position, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(x)):
            raise ValueError("scale model input contains NaN or inf")
        return x

    def update(self, xi_h: np.ndarray, phase=None, position=None) -> None:
        """Add one intervention's null-space actions ``xi_h`` (k, O) at their inputs and refit."""
        xi_h = np.asarray(xi_h, dtype=np.float64).reshape(-1, self.dim)
        if not np.all(np.isfinite(xi_h)):
            raise ValueError("xi_h contains NaN or inf")
        x = self._features(phase, position)
        if x.shape[0] != xi_h.shape[0]:
            raise ValueError(f"{xi_h.shape[0]} actions but {x.shape[0]} inputs")
        if xi_h.shape[0] == 0:
            return
        target = np.maximum(np.abs(xi_h) * self.config.margin, self.config.min_scale)
        self._x = np.concatenate([self._x, x])
        self._y = np.concatenate([self._y, np.log(target) - np.log(self.default)])
        self._thin()
        self._fit()
        self.n_updates += 1

    def _thin(self) -> None:
        """Keep at most max_points: average targets in bins of half a length scale (newest data wins ties)."""
        if self._x.shape[0] <= self.config.max_points:
            return
        keys = np.floor(self._x / (0.5 * self.config.length_scale)).astype(np.int64)
        _, inverse = np.unique(keys, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        count = np.bincount(inverse)
        x = np.stack([np.bincount(inverse, self._x[:, k]) / count for k in range(self._x.shape[1])], axis=1)
        y = np.stack([np.bincount(inverse, self._y[:, k]) / count for k in range(self._y.shape[1])], axis=1)
        newest = np.zeros(len(count), dtype=np.int64)
        np.maximum.at(newest, inverse, np.arange(inverse.size))  # latest sample index in each bin
        keep = np.sort(np.argsort(newest)[-self.config.max_points :])
        order = keep[np.argsort(newest[keep])]  # oldest to newest
        self._x, self._y = x[order], y[order]

    def _fit(self) -> None:
        c = self.config
        self._gp = GPR(c.signal_var, c.length_scale, c.noise_var).fit(self._x, self._y)

    def __call__(self, phase=None, position=None) -> np.ndarray:
        """L at the given input(s): (O,) for one input, (k, O) for k."""
        x = self._features(phase, position)
        if self._gp is None:
            out = np.broadcast_to(self.default, (x.shape[0], self.dim)).copy()
        else:
            log_l = self._gp.predict(x) + np.log(self.default)
            out = np.maximum(np.exp(log_l), self.config.min_scale)
        single = (np.ndim(phase) == 0) if self.config.input == "phase" else (np.ndim(position) == 1)
        return out[0] if single else out

    def table(self, phases: np.ndarray) -> np.ndarray:
        """L on a phase grid, (N, O): what the actor looks up every step (phase input only)."""
        if self.config.input != "phase":
            raise ValueError("a phase table needs a phase-input scale model")
        return self(phase=np.asarray(phases, dtype=np.float64).reshape(-1))

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        """Plain data for msgpack/JSON: the config, L0 and the (thinned) training data."""
        c = self.config
        return {
            "default": self.default.tolist(),
            "config": {k: getattr(c, k) for k in c.__dataclass_fields__},
            "x": self._x.tolist(),
            "y": self._y.tolist(),
            "n_updates": self.n_updates,
        }

    @classmethod
    def from_dict(cls, data: dict) -> "ScaleModel":
        model = cls(data["default"], config=ScaleConfig(**data["config"]))
        x = np.asarray(data["x"], dtype=np.float64).reshape(-1, model.in_dim)
        y = np.asarray(data["y"], dtype=np.float64).reshape(-1, model.dim)
        if x.shape[0] != y.shape[0] or not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise ValueError("scale model data is inconsistent or non-finite")
        model._x, model._y = x, y
        model.n_updates = int(data.get("n_updates", 0))
        if x.shape[0]:
            model._fit()
        return model
