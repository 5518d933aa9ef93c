"""How much each method needs to converge, KhGRL against HIL-SERL (``khgrl report EXP`` on a task's runs).

Each run's milestones (``first``, ``80/20``) and human budget: deploy/experiments/run_milestones.py. Per task, each
HIL-SERL arm against KhGRL (and, with both HIL-SERL arms, its recipe against its protocol: hypothesis C3 of
docs/results_vs_hilserl.md): the ratio of the seed means with a percentile bootstrap interval (seeds resampled
within each arm), the final policies' success over new scenes (Wilson), and the smallest one-sided Mann-Whitney p
that the seeds allow; and each run on a line of its own. Writes ``convergence.md``, ``convergence.csv`` and
``curves_<task>.png``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
from khgrl.common.tasks.passage.scenarios import SCENARIOS
from khgrl.deploy.experiments.figures import plot_curves
from khgrl.deploy.experiments.run_milestones import (
    MILESTONES,
    RATE,
    WINDOW,
    Milestone,
    RunConvergence,
    csv_rows,
    milestone_episode,
    run_convergence,
)
from khgrl.deploy.experiments.run_results import METHOD_LABEL
from khgrl.deploy.tools.intervals import rate_text

__all__ = ["MILESTONES", "METRICS", "HIL_ARMS", "Milestone", "RunConvergence", "milestone_episode",
           "run_convergence", "ratio_interval", "smallest_p", "write_convergence"]

METRICS = (("episodes", "episodes"), ("steps", "env steps"), ("human_steps", "human steps"), ("wall_s", "wall s"))
HIL_ARMS = ("hil-serl", "hil-serl_recipe")
RESAMPLES, BOOT_SEED = 10_000, 0


def ratio_interval(hil: list[float], khgrl: list[float], resamples: int = RESAMPLES,
                   seed: int = BOOT_SEED) -> tuple[float, float, float]:
    """(mean(hil) / mean(khgrl), 2.5 %, 97.5 % percentiles of the bootstrap ratio); each arm's seeds resampled
    independently. A KhGRL mean of 0 gives inf.

    :param hil: a HIL-SERL arm's values, one per seed.
    :param khgrl: KhGRL's values, one per seed.
    :param resamples: bootstrap resamples.
    :param seed: the generator's seed (a fixed seed: the same interval every time).
    """
    a, b = np.asarray(hil, dtype=np.float64), np.asarray(khgrl, dtype=np.float64)
    rng = np.random.default_rng(seed)
    ma = a[rng.integers(0, a.size, (resamples, a.size))].mean(axis=1)
    mb = b[rng.integers(0, b.size, (resamples, b.size))].mean(axis=1)
    point = a.mean() / b.mean() if b.mean() else math.inf
    r = np.where(mb > 0, ma / np.where(mb > 0, mb, 1.0), np.inf)
    lo, hi = np.percentile(r, [2.5, 97.5], method="nearest")
    return float(point), float(lo), float(hi)


def smallest_p(n1: int, n2: int) -> float:
    """The smallest one-sided Mann-Whitney p (exact, no ties) at n1 and n2 seeds: 1 / C(n1 + n2, n1).

    :param n1: seeds of one arm.
    :param n2: seeds of the other.
    """
    return 1.0 / math.comb(n1 + n2, n1)


def _num(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def _arm_cell(runs: list[RunConvergence], name: str, key: str) -> str:
    ms = [r.milestones[name] for r in runs]
    seeds = ", ".join(f"{'' if m.reached else '>'}{_num(getattr(m, key))}" for m in ms)
    return f"{'' if all(m.reached for m in ms) else '≥ '}{_num(np.mean([getattr(m, key) for m in ms]))} ({seeds})"


def _ratio_cell(num: list[RunConvergence], den: list[RunConvergence], name: str, key: str) -> str:
    if name == "whole run":  # the human budget of the whole runs: nothing censored
        if key != "human_steps":
            return ""
        point, lo, hi = ratio_interval([r.human_budget for r in num], [r.human_budget for r in den])
        return f"{_num(point)} [{_num(lo)}, {_num(hi)}]"
    point, lo, hi = ratio_interval([getattr(r.milestones[name], key) for r in num],
                                   [getattr(r.milestones[name], key) for r in den])
    reached = [r.milestones[name].reached for r in num]
    flag = "" if all(r.milestones[name].reached for r in den) else "†"
    if not any(reached):
        return f"> {_num(point)}{flag}"
    return f"{'' if all(reached) else '≥ '}{_num(point)} [{_num(lo)}, {_num(hi)}]{flag}"


def _ratio_table(title: str, pairs: list[tuple[str, str]], groups: dict[str, list[RunConvergence]]) -> list[str]:
    """Rows of ``numerator : denominator`` for each pair of arms, per milestone and for the whole run's human steps."""
    lines = [f"| {title} | milestone | {' | '.join(h for _, h in METRICS)} | min p |",
             "|---|---|" + "---|" * (len(METRICS) + 1)]
    for num, den in pairs:
        p = smallest_p(len(groups[num]), len(groups[den]))
        for name in (*MILESTONES, "whole run"):
            cells = " | ".join(_ratio_cell(groups[num], groups[den], name, k) for k, _ in METRICS)
            lines.append(f"| {METHOD_LABEL[num]} : {METHOD_LABEL[den]} | {name} | {cells} | {p:.3g} |")
    return [*lines, ""]


def _run_row(r: RunConvergence) -> str:
    """One run's line: its first autonomous success (the teacher's share of the human steps said), its 80/20 or
    what its last autonomous episodes did, and its autonomous successes."""
    first, window, counts = r.milestones["first"], r.milestones["80/20"], r.autonomous_counts()
    teacher = f" ({r.teacher_steps:,} of them the teacher's)" if r.teacher_steps else ""
    first_text = f"{first.episodes} / {first.human_steps:,}{teacher}" if first.reached else \
        f"none in {first.episodes} / {r.human_budget:,} spent"  # not reached: the values at the run's end
    last = "" if counts is None else f"; {counts[3]} of its last {counts[2]} autonomous succeeded"
    window_text = f"episode {window.episodes}{' (ended there)' if r.converged else ''}" if window.reached else \
        f"not reached in {window.episodes}{last}"
    auto = "?" if counts is None else f"{counts[1]} of {counts[0]}"
    return f"| {METHOD_LABEL.get(r.method, r.method)} | {r.seed} | {first_text} | {window_text} | {auto} |"


def _task_markdown(task: str, groups: dict[str, list[RunConvergence]]) -> list[str]:
    head = " | ".join(h for _, h in METRICS)
    rule = "|---|---|" + "---|" * (len(METRICS) + 1)
    lines = [f"## {task}", "", f"| method | milestone | {head} | converged |", rule]
    for method, runs in groups.items():
        for name in MILESTONES:
            cells = " | ".join(_arm_cell(runs, name, k) for k, _ in METRICS)
            lines.append(f"| {METHOD_LABEL.get(method, method)} | {name} | {cells} | "
                         f"{sum(r.converged for r in runs)}/{len(runs)} |")
    lines += ["", "| method | seed | first autonomous success: episode / human steps | 80 % over 20 autonomous | "
              "autonomous successes |", "|---|---|---|---|---|",
              *(_run_row(r) for runs in groups.values() for r in runs)]  # (write_convergence: in seed order)
    lines += ["", "Human budget of the whole run (intervention + teacher steps): " + "; ".join(
        f"{METHOD_LABEL.get(m, m)} {_num(np.mean([r.human_budget for r in rs]))} "
        f"({', '.join(str(r.human_budget) for r in rs)})" for m, rs in groups.items()), ""]
    pairs = [(arm, "khgrl") for arm in HIL_ARMS if arm in groups and "khgrl" in groups]
    if pairs:
        lines += _ratio_table("HIL-SERL arm : KhGRL", pairs, groups)
    if all(arm in groups for arm in HIL_ARMS):  # does the recipe matter (HIL-SERL against itself)?
        lines += _ratio_table("HIL-SERL's recipe : its protocol", [HIL_ARMS[::-1]], groups)
    evals = [(m, sum(r.evaluation[1] for r in rs), sum(r.evaluation[2] for r in rs),
              ", ".join(sorted({r.evaluation[0] for r in rs} - {""}))) for m, rs in groups.items()]
    if any(n for _, _, n, _ in evals):
        lines += ["| method | final success over new scenes, pooled over seeds | evaluated over |", "|---|---|---|",
                  *(f"| {METHOD_LABEL.get(m, m)} | {rate_text(k, n)} | {kinds} |" for m, k, n, kinds in evals if n), ""]
    return lines


NOTE = ("Milestones: 'first' the first autonomous success (no human step in the episode); '80/20' the episode that "
        f"completes the first window of {WINDOW} autonomous episodes with >= {RATE:.0%} successes. Cells: mean over "
        "seeds (per seed). '>N': the run never reached the milestone, N is its value at the run's "
        "end (a lower bound); '≥' a mean or ratio with such lower bounds in the HIL-SERL arm; '> X' every run of that "
        "arm censored. '†': some run of the arm after the colon censored too (its end value enters the mean; the ratio "
        "may be too high). Ratio = one arm's seed mean : another's (HIL-SERL arm : KhGRL; HIL-SERL's recipe : its "
        "protocol), whole run: the runs' human budgets; [2.5 %, 97.5 %] percentile "
        f"bootstrap over seeds (each arm resampled independently, {RESAMPLES} resamples, seed {BOOT_SEED}). Human "
        "steps = intervention steps + the teacher's steps driven; wall s = the episodes' wall time (not the "
        "teacher's). min p: the smallest one-sided Mann-Whitney p that n1 vs n2 seeds can give, 1 / C(n1 + n2, n1).")


def write_convergence(found: list[tuple[str, str, int, Path]], out: Path,
                      earlier: list[RunConvergence] = ()) -> str | None:
    """For each task (not a passage-world scenario) with runs of more than one method: ``convergence.md``,
    ``convergence.csv`` and ``curves_<task>.png`` in ``out``. Returns the markdown, None if no task qualifies.

    :param found: (task, method, seed, run dir) of the runs (:func:`~khgrl.deploy.experiments.run_results.find_runs`).
    :param out: the report's directory.
    :param earlier: runs of earlier reports (:func:`~khgrl.deploy.experiments.convergence_csv.load_report_runs`);
        one that is also among ``found`` is left out (the run at hand counts).
    """
    runs = [run_convergence(task, method, seed, run_dir) for task, method, seed, run_dir in found
            if task not in SCENARIOS]
    at_hand = {(r.task, r.method, r.seed) for r in runs}
    added = [r for r in earlier if r.task not in SCENARIOS and (r.task, r.method, r.seed) not in at_hand]
    tasks: dict[str, dict[str, list[RunConvergence]]] = {}
    for r in sorted(runs + added, key=lambda r: r.seed):
        tasks.setdefault(r.task, {}).setdefault(r.method, []).append(r)
    tasks = {t: {m: g[m] for m in sorted(g, key=lambda m: (m != "khgrl", m))} for t, g in tasks.items() if len(g) > 1}
    if not tasks:
        return None
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# Convergence: KhGRL against HIL-SERL", "", NOTE, "", *_earlier_note(added)]
    rows = csv_rows([r for _, groups in sorted(tasks.items()) for runs in groups.values() for r in runs])
    with open(out / "convergence.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    for task, groups in sorted(tasks.items()):
        lines += _task_markdown(task, groups)
        drawn = {m: [r for r in rs if r.rows is not None] for m, rs in groups.items()}
        if any(drawn.values()):  # the runs whose episodes are at hand
            plot_curves(task, {m: rs for m, rs in drawn.items() if rs}, out / f"curves_{task}.png")
    text = "\n".join(lines).rstrip("\n") + "\n"
    (out / "convergence.md").write_text(text)
    return text


def _earlier_note(added: list[RunConvergence]) -> list[str]:
    """The line that names the runs taken from earlier reports (no curve here: their episodes are not at hand)."""
    sources: dict[str, list[str]] = {}
    for r in added:
        sources.setdefault(r.source, []).append(f"{r.task}-{r.method}-seed{r.seed}")
    if not sources:
        return []
    named = "; ".join(f"{src}: {len(names)} runs" for src, names in sources.items())
    return [f"Runs of earlier reports, known by their convergence.csv (in the tables, not in the curves; '?': a "
            f"count that report did not keep): {named}.", ""]
