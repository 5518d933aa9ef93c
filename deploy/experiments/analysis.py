"""Analysis of an experiment (``khgrl experiment`` output): statistics across seeds and Fig. 4-6 of the paper.

An experiment directory holds one run directory per (scenario, method, seed), named
``<scenario>-<method>-seed<S>`` (``khgrl up`` runs: ``actor-a0/episodes.csv``; ``khgrl reference`` runs:
``episodes.csv``). :func:`analyse` reads them all and writes, into an output directory:

* ``per_run.csv``      one row per run: its learning criteria
* ``per_episode.csv``  per (scenario, method, episode) across seeds: mean, std, median, quartiles of return,
  obstacle cost and passage cost; success rate (the data behind the figures)
* ``scale.csv``        L over phase at the end of each run (Fig. 6 data)
* ``fig4_high_cov.png`` / ``fig5_low_cov.png``  return, obstacle cost, passage cost, success rate per episode
  (mean +- std band over seeds, human episodes shaded); ``fig6_scale.png`` L over phase
* ``summary.md``       the tables: per method and scenario, and KhGRL vs KGRL with a rank test
* ``convergence.md`` / ``convergence.csv`` / ``curves_<task>.png``  for each task with runs of more than one method:
  what each method needs to reach its milestones, HIL-SERL : KhGRL (``deploy/experiments/convergence.py``)

The learning criteria of one run (first success, stable success, zero obstacle cost from, ...) and the reading
of run directories are in ``deploy/experiments/run_results.py``, the figures in
``deploy/experiments/figures.py``, the markdown tables in
``deploy/experiments/summary_table.py``; this module puts them together and writes the CSV files.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
from khgrl.deploy.experiments.convergence import write_convergence
from khgrl.deploy.experiments.figures import axis_names, figure_name, plot_learning, plot_scale
from khgrl.deploy.experiments.run_milestones import load_report_runs
from khgrl.deploy.experiments.run_results import (
    METHOD_LABEL,
    STABLE_WINDOW,
    RunResult,
    corrected_phases,
    episode_matrix,
    find_runs,
    load_run,
    load_scale,
    stable_success,
    summarize_run,
    zero_cost_from,
)
from khgrl.deploy.experiments.summary_table import summary_markdown

__all__ = ["RunResult", "find_runs", "load_run", "stable_success", "zero_cost_from", "analyse", "STABLE_WINDOW"]

def analyse(exp_dirs: list[Path], out: Path, seeds: list[int] | None = None, scenarios: list[str] | None = None,
            earlier: list[Path] = ()) -> str:
    """Read every run of the experiment directories (optionally only some seeds / scenarios), write the tables and
    figures into ``out``; return summary.md.

    :param exp_dirs: experiment directories (``khgrl experiment`` output).
    :param out: the report's directory.
    :param seeds: only these seeds (default: all).
    :param scenarios: only these scenarios or task labels (default: all).
    :param earlier: directories of earlier reports whose runs (their ``convergence.csv``) join the convergence
        tables: runs whose directories are elsewhere or gone (:func:`load_report_runs`).
    """
    before = [r for d in earlier for r in load_report_runs(Path(d))
              if (seeds is None or r.seed in seeds) and (scenarios is None or r.task in scenarios)]
    found = [r for d in exp_dirs for r in find_runs(Path(d))
             if (seeds is None or r[2] in seeds) and (scenarios is None or r[0] in scenarios)]
    running = [r for r in found if _unfinished(r[3])]  # an experiment still running, or a run cut short
    found = [r for r in found if r not in running]
    if not found:
        raise FileNotFoundError(f"no run directories named <scenario>-<method>-seed<S> with finished results in "
                                f"{exp_dirs}")
    out.mkdir(parents=True, exist_ok=True)
    data: dict[tuple[str, str], list[list[dict]]] = {}
    results: list[RunResult] = []
    scales: dict[tuple[str, str], list] = {}
    for scenario, method, seed, run_dir in found:
        rows = load_run(run_dir)
        data.setdefault((scenario, method), []).append(rows)
        results.append(summarize_run(scenario, method, seed, run_dir, rows))
        phases, table, _ = load_scale(run_dir, scenario)
        scales.setdefault((scenario, method), []).append((phases, table, corrected_phases(run_dir, len(phases))))
    episodes = max(len(rows) for runs in data.values() for rows in runs)

    with open(out / "per_run.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(asdict(results[0])))
        w.writeheader()
        w.writerows(asdict(r) for r in results)
    _write_per_episode(data, episodes, out / "per_episode.csv")
    _write_scale(found, scales, out / "scale.csv")
    for scenario in sorted({k[0] for k in data}):
        name, title = figure_name(scenario)
        groups = {m: data[(scenario, m)] for m in METHOD_LABEL if (scenario, m) in data}
        plot_learning(scenario, groups, episodes, out / name, title)
    plot_scale(scales, out / "fig6_scale.png")
    text = summary_markdown(results, episodes)
    if running:
        names = ", ".join(r[3].name for r in running)
        text += f"\nLeft out, not finished (experiment.json: running or interrupted): {names}\n"
    (out / "summary.md").write_text(text)
    write_convergence(found, out, before)  # tasks with runs of several methods: convergence.md, .csv, curves_<task>.png
    return text


def _unfinished(run_dir: Path) -> bool:
    """Whether the experiment that made ``run_dir`` (its ``experiment.json``) says the run is still running or
    was interrupted: its episodes are not a result yet."""
    try:
        runs = json.loads((run_dir.parent / "experiment.json").read_text()).get("runs", {})
    except (OSError, ValueError, AttributeError):
        return False
    return isinstance(runs, dict) and runs.get(run_dir.name, {}).get("status") in ("running", "interrupted")


def _write_per_episode(data: dict, episodes: int, path: Path) -> None:
    keys = ("ret", "obstacle_cost", "passage_cost")
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        head = ["scenario", "method", "episode", "seeds"]
        for k in keys:
            head += [f"{k}_{s}" for s in ("mean", "std", "median", "q25", "q75")]
        w.writerow(head + ["success_rate", "human_seeds"])
        for (scenario, method), runs in sorted(data.items()):
            mats = {k: episode_matrix(runs, k, episodes) for k in (*keys, "success", "intervention_steps")}
            for e in range(episodes):
                col = {k: m[:, e][~np.isnan(m[:, e])] for k, m in mats.items()}
                if col["ret"].size == 0:
                    continue
                row = [scenario, method, e + 1, col["ret"].size]
                for k in keys:
                    v = col[k]
                    row += [f"{v.mean():.4f}", f"{v.std():.4f}", f"{np.median(v):.4f}",
                            f"{np.percentile(v, 25):.4f}", f"{np.percentile(v, 75):.4f}"]
                w.writerow(row + [f"{col['success'].mean():.4f}", int(np.sum(col["intervention_steps"] > 0))])


def _write_scale(found, scales, path: Path) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        outputs = max(table.shape[1] for items in scales.values() for _, table, _ in items)
        w.writerow(["scenario", "method", "seed", "phase", *(f"L_{a}" for a in axis_names(outputs))])
        index: dict[tuple[str, str], int] = {}
        for scenario, method, seed, _ in found:
            i = index.get((scenario, method), 0)
            index[(scenario, method)] = i + 1
            phases, table, _ = scales[(scenario, method)][i]
            for p, row in zip(phases, table):
                w.writerow([scenario, method, seed, f"{p:.5f}", *(f"{v:.6g}" for v in row),
                            *([""] * (outputs - len(row)))])


def experiment_config(exp_dir: Path) -> dict | None:
    """The experiment's recorded configuration and run statuses, if it was made by ``khgrl experiment``."""
    f = Path(exp_dir) / "experiment.json"
    return json.loads(f.read_text()) if f.exists() else None
