"""Figures of a fitted KMP model: what a person wants to see before training on it.

:func:`plot_kmp` draws, for any number of outputs O:

* O = 2: (1) the workspace with the demonstrations, GMR 2-sigma ellipses and the KMP mean, (2) each output
  over the phase with its band, (3) the soft null-space projector's magnitude over the phase;
* otherwise: the 2-D view of the first two outputs (O >= 2), one panel per output over the phase
  (demonstrations, GMR ±2σ band, KMP mean) and the projector's magnitude.

Axes are scaled to the data (the passage world's unit square when its scenario is drawn).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from khgrl.common.kmp.gmr import ReferenceDistribution  # noqa: E402
from khgrl.common.kmp.lcnskmp import LCNSKMP  # noqa: E402

__all__ = ["plot_kmp"]


def plot_kmp(
    model: LCNSKMP,
    ref: ReferenceDistribution | None,
    demos: np.ndarray,
    path: str | Path,
    *,
    title: str = "",
    scenario=None,
    names: Sequence[str] | None = None,
    workspace: tuple[Sequence[float], Sequence[float]] | None = None,
) -> Path:
    """Write the PNG described in the module docstring and return its path.

    :param model: the fitted LC-NS-KMP.
    :param ref: the GMR reference distribution (its 2σ band is drawn), or None.
    :param demos: (M, N, O) demonstrations.
    :param path: the PNG to write (parent directories are created).
    :param title: figure title.
    :param scenario: a passage-world scenario whose walls, obstacle, start and goal are drawn (O = 2).
    :param names: a name per output (default y0, y1, ...).
    :param workspace: (low, high) of a box drawn in the 2-D view (e.g. the hard box constraints).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    demos = np.asarray(demos, dtype=np.float64)
    o = model.grid_mean.shape[1]
    names = list(names) if names else [f"y{k}" for k in range(o)]
    if o == 2:
        fig, axes = plt.subplots(1, 3, figsize=(16, 5), constrained_layout=True)
        _workspace(axes[0], model, ref, demos, names, scenario, workspace)
        _outputs_together(axes[1], model, ref, names)
        _projector(axes[2], model)
    else:
        panels = (1 if o >= 2 else 0) + o + 1
        ncols = min(panels, 3 if panels <= 6 else 4)
        nrows = math.ceil(panels / ncols)
        fig, grid = plt.subplots(nrows, ncols, figsize=(4.6 * ncols, 3.8 * nrows), constrained_layout=True,
                                 squeeze=False)
        axes = list(grid.ravel())
        if o >= 2:
            _workspace(axes.pop(0), model, ref, demos, names, None, workspace)
        for k in range(o):
            _output(axes.pop(0), model, ref, demos, k, names[k])
        _projector(axes.pop(0), model)
        for ax in axes:
            ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _phase(model: LCNSKMP) -> np.ndarray:
    return np.asarray(model.s)[:, 0]


def _std(ref: ReferenceDistribution) -> np.ndarray:
    return np.sqrt(np.clip(np.diagonal(ref.sigma, axis1=1, axis2=2), 0.0, None))


def _limits(values: np.ndarray, pad: float = 0.05) -> tuple[float, float]:
    lo, hi = float(np.nanmin(values)), float(np.nanmax(values))
    span = hi - lo if hi > lo else max(1.0, abs(lo))
    return lo - pad * span, hi + pad * span


def _workspace(ax, model: LCNSKMP, ref: ReferenceDistribution | None, demos: np.ndarray, names: list[str],
               scenario, workspace) -> None:
    """The first two outputs against each other: demos (dashed), GMR 2σ ellipses, KMP mean."""
    mean = model.grid_mean
    for d in demos:
        ax.plot(d[:, 0], d[:, 1], "--", color="tab:blue", lw=0.8, alpha=0.7)
    pts = [demos[..., :2].reshape(-1, 2), mean[:, :2]]
    if ref is not None:
        theta = np.linspace(0, 2 * np.pi, 40)
        circle = np.stack([np.cos(theta), np.sin(theta)])
        for n in range(0, len(mean), max(1, len(mean) // 40)):
            w, v = np.linalg.eigh(ref.sigma[n][:2, :2])
            ell = ref.mu[n, :2][:, None] + 2.0 * (v * np.sqrt(np.clip(w, 0, None))) @ circle
            ax.fill(ell[0], ell[1], color="tab:gray", alpha=0.12, lw=0)
            pts.append(ell.T)
    ax.plot(mean[:, 0], mean[:, 1], color="red", lw=2, label="KMP mean")
    if workspace is not None:
        lo, hi = (np.asarray(v, dtype=np.float64)[:2] for v in workspace)
        ax.add_patch(plt.Rectangle(lo, *(hi - lo), fill=False, ls=":", color="k", lw=1, label="box"))
        pts.append(np.stack([lo, hi]))
    if scenario is not None:
        _draw_scenario(ax, scenario)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
    else:
        allp = np.concatenate(pts)
        ax.set_xlim(*_limits(allp[:, 0]))
        ax.set_ylim(*_limits(allp[:, 1]))
    spans = np.ptp(np.concatenate(pts), axis=0)
    if scenario is not None or (spans.min() > 0 and spans.max() / spans.min() < 4):
        ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(names[0])
    ax.set_ylabel(names[1])
    ax.set_title(f"{names[0]}-{names[1]}: demos (dashed), GMR 2σ, KMP mean")
    ax.legend(loc="best")


def _outputs_together(ax, model: LCNSKMP, ref: ReferenceDistribution | None, names: list[str]) -> None:
    s, mean = _phase(model), model.grid_mean
    for k in range(mean.shape[1]):
        if ref is not None:
            std = _std(ref)
            ax.fill_between(s, ref.mu[:, k] - 2 * std[:, k], ref.mu[:, k] + 2 * std[:, k], alpha=0.2, color=f"C{k}")
        ax.plot(s, mean[:, k], color=f"C{k}", lw=2, label=f"KMP mean {names[k]}")
    ax.set_xlabel("phase s")
    ax.set_title("outputs over time: KMP mean and GMR 2σ band")
    ax.legend()


def _output(ax, model: LCNSKMP, ref: ReferenceDistribution | None, demos: np.ndarray, k: int, name: str) -> None:
    """Output k over the phase: demonstrations (thin grey), GMR ±2σ, KMP mean (red)."""
    s, mean = _phase(model), model.grid_mean[:, k]
    values = [mean, demos[..., k].ravel()]
    for d in demos:
        ax.plot(np.linspace(0.0, 1.0, len(d)), d[:, k], color="0.55", lw=0.7, alpha=0.8)
    if ref is not None:
        std = _std(ref)[:, k]
        lo, hi = ref.mu[:, k] - 2 * std, ref.mu[:, k] + 2 * std
        ax.fill_between(s, lo, hi, alpha=0.25, color="tab:blue", lw=0, label="GMR ±2σ")
        values += [lo, hi]
    ax.plot(s, mean, color="red", lw=2, label="KMP mean")
    ax.set_ylim(*_limits(np.concatenate(values)))
    ax.set_xlim(0.0, 1.0)
    ax.set_xlabel("phase s")
    ax.set_ylabel(name)
    ax.set_title(f"{name} over the phase")
    ax.grid(True, alpha=0.3)
    if k == 0:
        ax.legend(loc="best", fontsize="small")


def _projector(ax, model: LCNSKMP) -> None:
    proj_norm = np.linalg.eigvalsh(model.grid_projector)[:, -1]
    ax.semilogy(_phase(model), proj_norm, color="k")
    ax.set_xlabel("phase s")
    ax.set_ylabel("largest eigenvalue of N(s)")
    ax.set_title("soft null-space projector magnitude (eq. 5)")
    ax.grid(True, which="both", alpha=0.3)


def _draw_scenario(ax, scenario) -> None:
    for wall in scenario.walls:
        ax.plot([wall.x, wall.x], [0, wall.gap_lo], color="k", lw=3)
        ax.plot([wall.x, wall.x], [wall.gap_hi, 1], color="k", lw=3)
        ax.fill_between([wall.x - 0.01, wall.x + 0.01], wall.gap_lo, wall.gap_hi, color="gold", alpha=0.6)
    if scenario.obstacle is not None:
        ax.add_patch(plt.Circle(scenario.obstacle.center, scenario.obstacle.radius, color="saddlebrown", alpha=0.6))
    ax.plot(*scenario.start, "o", color="purple", ms=9)
    ax.plot(*scenario.goal, "o", color="green", ms=9)
