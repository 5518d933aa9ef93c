"""``khgrl report``: results of runs or of whole experiments.

* Experiment directories (``khgrl experiment`` output: run directories named ``<scenario>-<method>-seed<S>``):
  statistics across seeds, Fig. 4-6 and the data behind them (:mod:`khgrl.deploy.experiments.analysis`), and for
  tasks run with several methods what each needs to converge (:mod:`khgrl.deploy.experiments.convergence`), written
  to ``--out`` (default ``EXP/report``); ``--with-report OLD`` adds the runs of an earlier report (its
  ``convergence.csv``) to the convergence tables.
* Run directories of ``khgrl reference`` (``RUN/episodes.csv``) or ``khgrl up`` (``RUN/actor-<id>/episodes.csv``,
  one series per actor): per-episode curves in one figure and a markdown table.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from khgrl.common.tasks.passage.scenarios import SCENARIOS

__all__ = ["main", "load_series", "summarize"]


def load_series(run_dir: Path) -> dict[str, list[dict]]:
    """{label: episode rows} for a run directory."""
    run_dir = Path(run_dir)
    files = [run_dir / "episodes.csv"]
    if not files[0].exists():
        files = sorted(run_dir.glob("actor-*/episodes.csv"))
    if not files:
        raise FileNotFoundError(f"{run_dir}: no episodes.csv (expected RUN/episodes.csv or RUN/actor-*/episodes.csv)")
    out = {}
    for f in files:
        label = run_dir.name if f.parent == run_dir else f"{run_dir.name}/{f.parent.name}"
        with open(f, newline="") as fh:
            out[label] = list(csv.DictReader(fh))
    return out


def summarize(rows: list[dict]) -> dict:
    succ = [r["success"] == "True" for r in rows]
    human = [int(r["intervention_steps"]) > 0 for r in rows]
    return {
        "episodes": len(rows),
        "successes": sum(succ),
        "first_success": next((int(r["episode"]) for r, s in zip(rows, succ) if s), None),
        "first_success_without_human": next(
            (int(r["episode"]) for r, s, h in zip(rows, succ, human) if s and not h), None
        ),
        "success_last_10": sum(succ[-10:]),
        "episodes_with_collision": sum(float(r["obstacle_cost"]) < 0 for r in rows),
        "human_episodes": sum(human),
        "clipped_human_steps": sum(int(r["clipped_steps"]) for r in rows),
        "mean_return_last_10": sum(float(r["ret"]) for r in rows[-10:]) / max(1, len(rows[-10:])),
    }


def plot(series: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(10, 9), sharex=True, constrained_layout=True)
    for k, (label, rows) in enumerate(series.items()):
        ep = [int(r["episode"]) for r in rows]
        color = f"C{k}"
        axes[0].plot(ep, [float(r["ret"]) for r in rows], color=color, label=label)
        hs = [(e, float(r["ret"])) for e, r in zip(ep, rows) if int(r["intervention_steps"]) > 0]
        if hs:
            axes[0].scatter(*zip(*hs), color=color, marker="^", s=30)
        axes[1].plot(ep, [float(r["obstacle_cost"]) for r in rows], color=color)
        axes[2].plot(ep, [float(r["passage_cost"]) for r in rows], color=color)
    axes[0].set_ylabel("return (▲ human episodes)")
    axes[1].set_ylabel("obstacle cost")
    axes[2].set_ylabel("passage cost")
    axes[2].set_xlabel("episode")
    axes[0].legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def markdown_table(series: dict[str, list[dict]]) -> str:
    cols = ["run", "successes", "first success", "first success w/o human", "success last 10", "collision episodes",
            "human episodes", "clipped human steps", "mean return last 10"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for label, rows in series.items():
        s = summarize(rows)
        lines.append(f"| {label} | {s['successes']}/{s['episodes']} | {s['first_success'] or '-'} | "
                     f"{s['first_success_without_human'] or '-'} | {s['success_last_10']}/10 | "
                     f"{s['episodes_with_collision']} | {s['human_episodes']} | {s['clipped_human_steps']} | "
                     f"{s['mean_return_last_10']:.1f} |")
    return "\n".join(lines)


def _report_experiments(args: argparse.Namespace, experiments: list[str]) -> int:
    """``khgrl report EXP ...``: the experiments' tables and figures (and earlier reports' runs, ``--with-report``)."""
    from khgrl.deploy.experiments.analysis import analyse

    out = Path(args.out or Path(experiments[0]) / "report")
    if any(Path(d).resolve() == out.resolve() for d in args.with_report):
        print(f"khgrl report: error: --out {out} is a report given to --with-report; it would be overwritten by "
              "one whose summary holds only the runs at hand: write to another directory", file=sys.stderr)
        return 2
    try:
        print(analyse([Path(r) for r in experiments], out, seeds=args.seeds, scenarios=args.scenarios,
                      earlier=[Path(d) for d in args.with_report]))
    except (FileNotFoundError, ValueError) as exc:
        print(f"khgrl report: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}/: summary.md, per_run.csv, per_episode.csv, scale.csv, fig6_scale.png and the learning "
          "curves of each scenario (fig4_high_cov.png, fig5_low_cov.png, learning_<task>.png); for tasks with runs "
          "of several methods convergence.md, convergence.csv and curves_<task>.png")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="khgrl report", description="Results of experiments (statistics across seeds, "
                                "Fig. 4-6) or of single runs (per-episode curves and a table).")
    p.add_argument("runs", nargs="+",
                   help="experiment directories (khgrl experiment) or run directories (khgrl up / reference)")
    p.add_argument("--out", default=None, help="experiments: output directory (default EXP/report); runs: the figure "
                                                "(default runs/report.png; the table is written beside it as .md)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="experiments: only these seeds")
    p.add_argument("--scenarios", nargs="+", default=None,
                   help=f"experiments: only these scenarios ({', '.join(SCENARIOS)}) or task labels (fetch_moved, "
                        "...) (default: all)")
    p.add_argument("--with-report", nargs="+", default=(), metavar="DIR",
                   help="experiments: earlier reports' directories whose runs (their convergence.csv) join the "
                        "convergence tables, for runs whose directories are elsewhere or gone (default: none)")
    args = p.parse_args(argv)
    from khgrl.deploy.experiments.analysis import find_runs

    missing = [r for r in args.runs if not Path(r).is_dir()]
    if missing:
        print(f"khgrl report: error: not a directory: {', '.join(missing)}", file=sys.stderr)
        return 2
    experiments = [r for r in args.runs if find_runs(Path(r))]
    if experiments and len(experiments) != len(args.runs):
        print("khgrl report: error: give either experiment directories or run directories, not both", file=sys.stderr)
        return 2
    if args.with_report and not experiments:
        print("khgrl report: error: --with-report joins an earlier report's runs to experiment directories' runs; "
              "give experiment directories", file=sys.stderr)
        return 2
    if experiments:
        return _report_experiments(args, experiments)
    args.out = args.out or "runs/report.png"
    series: dict[str, list[dict]] = {}
    try:
        for run in args.runs:
            for label, rows in load_series(Path(run)).items():
                if label in series:  # same run name in another folder: qualify it with the folder
                    label = f"{Path(run).resolve().parent.name}/{label}"
                series[label] = rows
    except FileNotFoundError as exc:
        print(f"khgrl report: error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    plot(series, out)
    table = markdown_table(series)
    out.with_suffix(".md").write_text(table + "\n")
    print(table)
    print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0
