"""The markdown summary of an experiment (``summary.md`` of ``khgrl report EXP``): per method and scenario, and
KhGRL vs KGRL with a one-sided Mann-Whitney U test, and the evaluation of the final policies (over seeded scenes
with Wilson intervals, or labelled "one scene"). Episode criteria are medians over seeds with 'never' (not
within the run) ranked last."""

from __future__ import annotations

from typing import Callable

import numpy as np
from khgrl.deploy.experiments.run_results import METHOD_LABEL, STABLE_WINDOW, RunResult
from khgrl.deploy.tools.intervals import wilson_interval

__all__ = ["summary_markdown", "median_text", "fmt_episode", "eval_cell"]


def _censored(v: int | None, episodes: int) -> int:
    """'never within the run' ranks after every episode of the run."""
    return episodes + 1 if v is None else v


def median_text(values: list[int | None], episodes: int) -> str:
    """Median over seeds with 'never' ranked last; a median between an episode and 'never' is shown as a range."""
    x = sorted(_censored(v, episodes) for v in values)
    lo, hi = x[(len(x) - 1) // 2], x[len(x) // 2]
    name = lambda v: "never" if v > episodes else f"{v:g}"  # noqa: E731
    if lo == hi or (lo <= episodes and hi <= episodes):
        return name((lo + hi) / 2)
    return f"{name(lo)}–{name(hi)}"


def fmt_episode(values: list[int | None], episodes: int) -> str:
    """'median (per seed: ...)', seeds in order; 'never' = not within the run."""
    per_seed = ", ".join("never" if v is None else str(v) for v in values)
    return f"{median_text(values, episodes)} ({per_seed})"


def _compare(a: list[int | None], b: list[int | None], episodes: int) -> float:
    """One-sided Mann-Whitney U p-value that the episodes in ``a`` come earlier than in ``b`` ('never' ranks last)."""
    from scipy.stats import mannwhitneyu

    xa = [_censored(v, episodes) for v in a]
    xb = [_censored(v, episodes) for v in b]
    if len(set(xa + xb)) == 1:
        return 1.0
    return float(mannwhitneyu(xa, xb, alternative="less").pvalue)


def _columns(results: list[RunResult], episodes: int) -> list[tuple[str, Callable[[list[RunResult]], str]]]:
    """(header, cell of a group of runs) of the table's columns; the obstacle columns only where some run has an
    obstacle cost, the evaluation column only where some run was evaluated (``khgrl eval``)."""
    def last10(rs: list[RunResult]) -> str:
        last = np.array([r.success_last_10 for r in rs])
        return f"{last.mean():.0%} ± {last.std():.0%} ({', '.join(f'{v:.0%}' for v in last)})"

    def episode(attr: str) -> Callable[[list[RunResult]], str]:
        return lambda rs: fmt_episode([getattr(r, attr) for r in rs], episodes)

    mean_sd = lambda v: f"{np.mean(v):.1f} ± {np.std(v):.1f}"  # noqa: E731
    cols = [("success, last 10 (mean ± std; per seed)", last10), ("first success", episode("first_success")),
            ("first success w/o human", episode("first_success_without_human")),
            (f"stable success ({STABLE_WINDOW} in a row)", episode("stable_success"))]
    if any(r.collision_episodes or r.obstacle_steps for r in results):
        cols += [("zero obstacle cost from", episode("zero_obstacle_cost_from")),
                 ("collision episodes", lambda rs: f"{np.mean([r.collision_episodes for r in rs]):.1f} "
                                                   f"({', '.join(str(r.collision_episodes) for r in rs)})")]
    cols += [("human episodes", lambda rs: f"{np.mean([r.human_episodes for r in rs]):.1f}"),
             ("clipped / human steps", lambda rs: f"{sum(r.clipped_human_steps for r in rs)} / "
                                                  f"{sum(r.intervention_steps for r in rs)}"),
             ("return, last 10", lambda rs: mean_sd([r.mean_return_last_10 for r in rs]))]
    if _budgeted(results):  # human budget, safety, compute
        cols += _budget_columns()
    if any(r.eval_success is not None for r in results):
        header = ("eval success of the final policy (mean; per seed)" if all(r.eval_kind in ("", "episodes")
                  for r in results) else "eval success of the final policy (scenes: pooled over seeds, 95 % Wilson "
                                         "CI; per seed)")
        cols.append((header, eval_cell))
    return cols


def _budgeted(results: list[RunResult]) -> bool:
    """Whether the comparison with HIL-SERL is in these results (its methods or RLPD replay): its columns and
    criteria."""
    return any(r.method.startswith("hil-serl") or r.method.endswith("_rlpd") for r in results)


STEP_CRITERIA = ("human_steps_to_first_autonomous",)  # compared as the episode criteria, in human steps
STEPS_BOUND = 10**9  # no run spends more human steps: 'never' ranks above it


def _budget_columns() -> list[tuple[str, Callable[[list[RunResult]], str]]]:
    """The comparison with HIL-SERL's columns: human steps spent before the first autonomous success, safety
    (hard-constraint violations, workspace exits of the policy) and compute (gradient steps, wall time)."""
    def human_to_first(rs: list[RunResult]) -> str:  # (as an episode criterion, 'never' ranked last)
        return fmt_episode([r.human_steps_to_first_autonomous for r in rs], STEPS_BOUND)

    def total(attr: str) -> Callable[[list[RunResult]], str]:
        return lambda rs: (f"{np.mean([getattr(r, attr) for r in rs]):.0f} "
                           f"({', '.join(str(getattr(r, attr)) for r in rs)})")

    def compute(rs: list[RunResult]) -> str:
        steps = [r.gradient_steps for r in rs if r.gradient_steps is not None]
        wall = [r.wall_s for r in rs if r.wall_s is not None]
        return (f"{np.mean(steps):.0f}" if steps else "-") + " / " + (f"{np.mean(wall):.0f} s" if wall else "-")

    return [("human steps before first autonomous success (median; per seed)", human_to_first),
            ("hard-constraint violation steps (mean; per seed)", total("violation_steps")),
            ("workspace exits (mean; per seed)", total("workspace_exits")),
            ("gradient steps / wall time (mean)", compute)]


def _run_eval(r: RunResult) -> str:
    """One run's evaluation in a cell: k/n with its Wilson interval over scenes, yes/no on one scene, else a rate."""
    if r.eval_success is None:
        return "-"
    if r.eval_kind == "scenes":
        low, high = wilson_interval(r.eval_successes, r.eval_episodes)
        return f"{r.eval_successes}/{r.eval_episodes} = {r.eval_success:.0%} ({low:.0%}–{high:.0%})"
    if r.eval_kind == "one scene":
        return {0: "no", r.eval_episodes: "yes"}.get(r.eval_successes, f"{r.eval_successes}/{r.eval_episodes}")
    return f"{r.eval_success:.0%}"


def eval_cell(rs: list[RunResult]) -> str:
    """The evaluation of a group of runs (seeds): over scenes the pooled rate with its Wilson interval and each
    seed's; on a fixed scene "one scene" and whether each seed's rollout succeeded (not a rate); else (``khgrl eval``
    over episodes) the mean rate and each seed's.

    :param rs: the runs, in seed order.
    """
    done = [r for r in rs if r.eval_success is not None]
    if not done:
        return "-"
    per_seed = ", ".join(_run_eval(r) for r in rs)
    kinds = {r.eval_kind for r in done}
    if kinds == {"scenes"}:
        k, n = sum(r.eval_successes for r in done), sum(r.eval_episodes for r in done)
        low, high = wilson_interval(k, n)
        return f"{k / n:.0%} ({low:.0%}–{high:.0%}; {k}/{n} scenes) (per seed: {per_seed})"
    if kinds == {"one scene"}:
        solved = sum(r.eval_successes == r.eval_episodes for r in done)
        return f"one scene, not a rate: solved by {solved} of {len(done)} seeds ({per_seed})"
    if kinds == {"episodes"}:
        return f"{np.mean([r.eval_success for r in done]):.0%} ({per_seed}; {rs[0].eval_episodes} episodes)"
    mixed = ", ".join(f"{r.eval_kind or '-'}: {_run_eval(r)}" for r in rs)
    return f"mixed evaluations (per seed: {mixed})"


def _higher(a: list[float], b: list[float]) -> str:
    """Mean difference and the one-sided Mann-Whitney U p-value that ``a`` is higher than ``b``."""
    from scipy.stats import mannwhitneyu

    p = 1.0 if len(set(a + b)) == 1 else float(mannwhitneyu(a, b, alternative="greater").pvalue)
    return f"{np.mean(a) - np.mean(b):+.0%} (p = {p:.3f})"


def summary_markdown(results: list[RunResult], episodes: int) -> str:
    groups: dict[tuple[str, str], list[RunResult]] = {}
    for r in results:
        groups.setdefault((r.scenario, r.method), []).append(r)
    cols = _columns(results, episodes)
    lines = [f"Episodes per run: {episodes}. Episode criteria: median over seeds ('never' = not within the run, ranked "
             "last; a median between an episode and 'never' is shown as a range), then each seed's value in seed "
             "order.",
             "",
             "| scenario | method | seeds | " + " | ".join(h for h, _ in cols) + " |", "|" + "---|" * (len(cols) + 3)]
    for (scenario, method), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r.seed)
        lines.append(f"| {scenario} | {METHOD_LABEL[method]} | {', '.join(str(r.seed) for r in rs)} | "
                     + " | ".join(cell(rs) for _, cell in cols) + " |")
    criteria = ["first_success_without_human", "stable_success"]
    if any(h == "zero obstacle cost from" for h, _ in cols):
        criteria.append("zero_obstacle_cost_from")
    if _budgeted(results):
        criteria += list(STEP_CRITERIA)
    # (a fixed scene's evaluation is one rollout repeated: not compared as a success rate)
    evaluated = (all(r.eval_success is not None for r in results)
                 and any(r.eval_kind != "one scene" for r in results))
    heads = [c.replace("_", " ").replace("without", "w/o") for c in criteria] + ["success, last 10"] + (
        ["eval success"] if evaluated else [])
    comp: list[str] = []
    for a_method, b_method in COMPARISONS:
        comp += _comparison(groups, a_method, b_method, criteria, heads, evaluated, episodes)
    return "\n".join(lines + comp) + "\n"


# (a, b): "a vs b" tables, where both ran: what the human adds (KhGRL vs KGRL, with and without adaptation) and
# what adapting the KMP to the scene adds (KGRL vs KGRL without adaptation)
COMPARISONS = (("khgrl", "kgrl"), ("kgrl", "kgrl_noadapt"), ("khgrl_noadapt", "kgrl_noadapt"), ("khgrl", "hil-serl"),
               ("khgrl_rlpd", "hil-serl"), ("khgrl_rlpd", "khgrl"), ("khgrl", "hil-serl_episode"),
               ("khgrl", "hil-serl_recipe"), ("hil-serl_recipe", "hil-serl"))


def _comparison(groups: dict, a_method: str, b_method: str, criteria: list[str], heads: list[str], evaluated: bool,
                episodes: int) -> list[str]:
    """The markdown lines of one "a vs b" table (none if no scenario has runs of both methods)."""
    a_name, b_name = METHOD_LABEL[a_method], METHOD_LABEL[b_method]
    rows = []
    for scenario in sorted({k[0] for k in groups}):
        a, b = groups.get((scenario, a_method)), groups.get((scenario, b_method))
        if not a or not b:
            continue
        cells = []
        for attr in criteria:
            va, vb = [getattr(r, attr) for r in a], [getattr(r, attr) for r in b]
            bound = STEPS_BOUND if attr in STEP_CRITERIA else episodes  # (criteria in human steps, not episodes)
            p = _compare(va, vb, bound)
            cells.append(f"{median_text(va, bound)} vs {median_text(vb, bound)} (p = {p:.3f})")
        cells.append(_higher([r.success_last_10 for r in a], [r.success_last_10 for r in b]))
        if evaluated and any(r.eval_kind == "one scene" for r in a + b):
            cells.append("one scene (not compared)")
        elif evaluated:
            cells.append(_higher([r.eval_success for r in a], [r.eval_success for r in b]))
        rows.append(f"| {scenario} | {len(a)}/{len(b)} | " + " | ".join(cells) + " |")
    if not rows:
        return []
    return ["", f"{a_name} vs {b_name} (episode criteria: median {a_name} vs median {b_name} over seeds, 'never' "
                f"ranked last, and the one-sided Mann–Whitney U p-value that {a_name}'s episodes come earlier; "
                f"success rates: mean {a_name} − mean {b_name} and the one-sided p-value that {a_name}'s is "
                f"higher):", "",
            f"| scenario | seeds ({a_name}/{b_name}) | " + " | ".join(heads) + " |",
            "|---|---|" + "---|" * len(heads), *rows]
