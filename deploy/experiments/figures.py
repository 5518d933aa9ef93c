"""Fig. 4-6 of the paper from an experiment's runs (``khgrl report EXP``): learning curves and the scale L; per-seed
success curves of a task's runs against episode and human steps (``curves_<task>.png``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from khgrl.deploy.experiments.run_results import METHOD_LABEL, episode_matrix, human_episodes

__all__ = ["FIGURE", "METHOD_COLOR", "figure_name", "plot_learning", "plot_scale", "axis_names", "plot_curves"]

METHOD_COLOR = {"khgrl": "C3", "kgrl": "C0", "khgrl_noadapt": "C1", "kgrl_noadapt": "C7", "khgrl_rlpd": "C5",
                "kgrl_rlpd": "C9", "hil-serl": "C2", "hil-serl_episode": "C8",
                "hil-serl_recipe": "C4"}
FIGURE = {"high_cov": ("fig4_high_cov.png", "Fig. 4 (high-covariance scenario A)"),
          "low_cov": ("fig5_low_cov.png", "Fig. 5 (low-covariance scenario B)")}


def _seeds(n: int) -> str:
    return f"{n} seed{'' if n == 1 else 's'}"


def figure_name(scenario: str) -> tuple[str, str]:
    """(file name, title) of a scenario's learning-curve figure: the paper's Fig. 4/5, or ``learning_<task>.png``."""
    return FIGURE.get(scenario, (f"learning_{scenario}.png", scenario))


def axis_names(outputs: int) -> str:
    """Names of the outputs' axes in labels: x, y, z (or 0, 1, ... beyond three)."""
    return "xyz" if outputs <= 3 else "".join(str(i) for i in range(outputs))


def plot_learning(scenario: str, groups: dict[str, list[list[dict]]], episodes: int, path: Path, title: str) -> None:
    """Return, obstacle cost, passage cost and success rate per episode: mean +- std over seeds per method (the
    cost panels only where some run has a cost: a task without an obstacle has none)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("ret", "return"), ("obstacle_cost", "obstacle cost"), ("passage_cost", "passage cost"),
            ("success", "success rate")]
    keys = [(k, name) for k, name in keys if k in ("ret", "success")
            or any(r[k] != 0 for runs in groups.values() for rows in runs for r in rows)]
    fig, axes = plt.subplots(len(keys), 1, figsize=(9, 2.5 * len(keys)), sharex=True, constrained_layout=True)
    ep = np.arange(1, episodes + 1)
    for method, runs in groups.items():
        color, label = METHOD_COLOR[method], f"{METHOD_LABEL[method]} ({_seeds(len(runs))})"
        for ax, (key, _) in zip(axes, keys):
            m = episode_matrix(runs, key, episodes)
            mean = np.nanmean(m, axis=0)
            ax.plot(ep, mean, color=color, label=label, lw=1.6)
            if key != "success":
                std = np.nanstd(m, axis=0)
                ax.fill_between(ep, mean - std, mean + std, color=color, alpha=0.18, lw=0)
        if method.startswith("khgrl"):
            for h in human_episodes(runs):
                for ax in axes:
                    ax.axvspan(h - 0.5, h + 0.5, color="0.85", zorder=0, lw=0)
    for ax, (_, name) in zip(axes, keys):
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[-1].set_ylim(-0.05, 1.05)
    axes[-1].set_xlabel("episode (grey: episodes with scripted human corrections, KhGRL)")
    axes[0].legend(loc="lower right", fontsize=9)
    axes[0].set_title(f"{title}: mean ± std over seeds")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_scale(scales: dict, path: Path) -> None:
    """Fig. 6: L of each output (L_x, L_y, ...) over phase at the end of each run, per scenario; where the human
    intervened, shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from khgrl.common.tasks.passage.scenarios import SCENARIOS, get_scenario

    scenarios = sorted({k[0] for k in scales})
    outputs = max(table.shape[1] for items in scales.values() for _, table, _ in items)
    fig, axes = plt.subplots(len(scenarios), outputs, figsize=(5.5 * outputs, 3.6 * len(scenarios)), squeeze=False,
                             constrained_layout=True)
    for row, scenario in enumerate(scenarios):
        for (sc, method), items in sorted(scales.items()):
            if sc != scenario:
                continue
            for i, (phases, table, corrected) in enumerate(items):
                for d, ax in enumerate(axes[row][:table.shape[1]]):
                    ax.plot(phases, table[:, d], color=METHOD_COLOR[method], lw=1.0, alpha=0.8,
                            label=f"{METHOD_LABEL[method]} ({len(items)} seeds)" if i == 0 else None)
                    if method == "khgrl" and corrected.size:
                        ax.axvspan(corrected.min(), corrected.max(), color="0.9", zorder=0, lw=0)
        note = "grey: phases the human corrected" + (
            "; L is not learned here, as in the paper"
            if scenario in SCENARIOS and not get_scenario(scenario).learn_scale else "")
        for d, ax in enumerate(axes[row]):
            ax.set_title(f"{scenario}: L_{axis_names(outputs)[d]} at the end of each run ({note})", fontsize=9)
            ax.set_xlabel("phase s")
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
        axes[row][0].legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _rolling(x: np.ndarray, k: int = 10) -> np.ndarray:
    c = np.cumsum(np.insert(x.astype(np.float64), 0, 0.0))
    i = np.arange(1, x.size + 1)
    return (c[i] - c[np.maximum(0, i - k)]) / np.minimum(i, k)


def plot_curves(task: str, groups: dict[str, list], path: Path) -> None:
    """Per method (columns): each seed's success (rolling mean over 10 episodes) against episode (top) and against
    cumulative human steps, the teacher's at the start (bottom; each row one x scale); a run ended by
    --until-success ends with a star.

    :param task: the task's label (the title).
    :param groups: {method: its runs}, each with ``seed``, ``rows`` (episode rows with ``success`` and
        ``intervention_steps``), ``teacher_steps`` and ``converged`` (``convergence.RunConvergence``).
    :param path: the PNG written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(groups), figsize=(4.5 * len(groups), 6), squeeze=False, sharex="row",
                             sharey=True, constrained_layout=True)
    for col, (method, runs) in enumerate(groups.items()):
        marked = False
        for k, run in enumerate(runs):
            succ = _rolling(np.array([r["success"] for r in run.rows], dtype=bool))
            human = run.teacher_steps + np.cumsum([r["intervention_steps"] for r in run.rows])
            for ax, x, draw in zip(axes[:, col], (np.arange(1, succ.size + 1), human), ("default", "steps-post")):
                ax.plot(x, succ, lw=0.8, color=f"C{k % 10}", label=f"seed {run.seed}", drawstyle=draw)
                if run.converged and succ.size:
                    ax.plot(x[-1], succ[-1], "*", ms=9, color=f"C{k % 10}", label=None if marked else "converged")
            marked = marked or (run.converged and bool(succ.size))
        axes[0, col].set_title(f"{METHOD_LABEL.get(method, method)} ({_seeds(len(runs))})", fontsize=10)
        axes[0, col].set_xlabel("episode")
        axes[1, col].set_xlabel("human steps (cumulative; teacher's at the start)")
        axes[0, col].legend(fontsize=7)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        ax.set_ylim(-0.05, 1.05)
    for ax in axes[:, 0]:
        ax.set_ylabel("success (mean of last 10)")
    fig.suptitle(f"{task}: success per seed (★ converged: ended by --until-success)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
