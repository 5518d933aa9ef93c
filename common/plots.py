"""Figures of a fitted KMP model: what a person wants to see before training on it."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common.gmr import ReferenceDistribution  # noqa: E402
from common.kmp import LCNSKMP  # noqa: E402

__all__ = ["plot_kmp"]


def plot_kmp(
    model: LCNSKMP,
    ref: ReferenceDistribution,
    demos: np.ndarray,
    path: str | Path,
    *,
    title: str = "",
    scenario=None,
) -> Path:
    """Write a 3-panel PNG: (1) demonstrations, GMR 2-sigma band and KMP mean in the workspace (2-D
    outputs) or per output over time; (2) each output over time with its band; (3) the projector's largest
    eigenvalue ||N(s)|| over time on a log scale -- how far the RL action can move the trajectory.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    s = ref.s[:, 0]
    mean = model.grid_mean
    std = np.sqrt(np.clip(np.diagonal(ref.sigma, axis1=1, axis2=2), 0.0, None))
    proj_norm = np.linalg.eigvalsh(model.grid_projector)[:, -1]
    o = mean.shape[1]

    fig, axes = plt.subplots(1, 3, figsize=(16, 5), constrained_layout=True)
    ax = axes[0]
    if o == 2:
        for d in demos:
            ax.plot(d[:, 0], d[:, 1], "--", color="tab:blue", lw=0.8, alpha=0.7)
        # 2-sigma ellipses every few points
        theta = np.linspace(0, 2 * np.pi, 40)
        circle = np.stack([np.cos(theta), np.sin(theta)])
        for n in range(0, len(s), max(1, len(s) // 40)):
            w, v = np.linalg.eigh(ref.sigma[n])
            ell = ref.mu[n][:, None] + 2.0 * (v * np.sqrt(np.clip(w, 0, None))) @ circle
            ax.fill(ell[0], ell[1], color="tab:gray", alpha=0.12, lw=0)
        ax.plot(mean[:, 0], mean[:, 1], color="red", lw=2, label="KMP mean")
        if scenario is not None:
            _draw_scenario(ax, scenario)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        ax.set_title("workspace: demos (dashed), GMR 2σ, KMP mean")
        ax.legend(loc="lower right")
    else:
        ax.axis("off")

    ax = axes[1]
    for k in range(o):
        ax.fill_between(s, ref.mu[:, k] - 2 * std[:, k], ref.mu[:, k] + 2 * std[:, k], alpha=0.2, color=f"C{k}")
        ax.plot(s, mean[:, k], color=f"C{k}", lw=2, label=f"KMP mean y{k}")
    ax.set_xlabel("phase s")
    ax.set_title("outputs over time: KMP mean and GMR 2σ band")
    ax.legend()

    ax = axes[2]
    ax.semilogy(s, proj_norm, color="k")
    ax.set_xlabel("phase s")
    ax.set_ylabel("largest eigenvalue of N(s)")
    ax.set_title("soft null-space projector magnitude (eq. 5)")
    ax.grid(True, which="both", alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _draw_scenario(ax, scenario) -> None:
    for wall in scenario.walls:
        ax.plot([wall.x, wall.x], [0, wall.gap_lo], color="k", lw=3)
        ax.plot([wall.x, wall.x], [wall.gap_hi, 1], color="k", lw=3)
        ax.fill_between([wall.x - 0.01, wall.x + 0.01], wall.gap_lo, wall.gap_hi, color="gold", alpha=0.6)
    if scenario.obstacle is not None:
        ax.add_patch(plt.Circle(scenario.obstacle.center, scenario.obstacle.radius, color="saddlebrown", alpha=0.6))
    ax.plot(*scenario.start, "o", color="purple", ms=9)
    ax.plot(*scenario.goal, "o", color="green", ms=9)
