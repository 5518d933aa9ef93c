"""The markdown summary of an experiment (``summary.md`` of ``khgrl report EXP``): per method and scenario, and
KhGRL vs KGRL with a one-sided Mann-Whitney U test. Episode criteria are medians over seeds with 'never' (not
within the run) ranked last."""

from __future__ import annotations

import numpy as np

from deploy.run_results import METHOD_LABEL, STABLE_WINDOW, RunResult

__all__ = ["summary_markdown", "median_text", "fmt_episode"]


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


def summary_markdown(results: list[RunResult], episodes: int) -> str:
    groups: dict[tuple[str, str], list[RunResult]] = {}
    for r in results:
        groups.setdefault((r.scenario, r.method), []).append(r)
    cols = ["scenario", "method", "seeds", "success, last 10 (mean ± std; per seed)", "first success",
            "first success w/o human", f"stable success ({STABLE_WINDOW} in a row)", "zero obstacle cost from",
            "collision episodes", "human episodes", "clipped / human steps", "return, last 10"]
    lines = [f"Episodes per run: {episodes}. Episode criteria: median over seeds ('never' = not within the run, ranked "
             "last; a median between an episode and 'never' is shown as a range), then each seed's value in seed "
             "order.",
             "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for (scenario, method), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r.seed)
        last = np.array([r.success_last_10 for r in rs])
        per_seed = ", ".join(f"{v:.0%}" for v in last)
        iv = sum(r.intervention_steps for r in rs)
        lines.append(
            f"| {scenario} | {METHOD_LABEL[method]} | {', '.join(str(r.seed) for r in rs)} | "
            f"{last.mean():.0%} ± {last.std():.0%} ({per_seed}) | "
            f"{fmt_episode([r.first_success for r in rs], episodes)} | "
            f"{fmt_episode([r.first_success_without_human for r in rs], episodes)} | "
            f"{fmt_episode([r.stable_success for r in rs], episodes)} | "
            f"{fmt_episode([r.zero_obstacle_cost_from for r in rs], episodes)} | "
            f"{np.mean([r.collision_episodes for r in rs]):.1f} ({', '.join(str(r.collision_episodes) for r in rs)}) | "
            f"{np.mean([r.human_episodes for r in rs]):.1f} | "
            f"{sum(r.clipped_human_steps for r in rs)} / {iv} | "
            f"{np.mean([r.mean_return_last_10 for r in rs]):.1f} ± {np.std([r.mean_return_last_10 for r in rs]):.1f} |")
    comp = ["", "KhGRL vs KGRL (episode criteria: median KhGRL vs median KGRL over seeds, 'never' ranked last, and "
                "the one-sided Mann–Whitney U p-value that KhGRL's episodes come earlier; success rate over the last "
                "10: mean KhGRL − mean KGRL and the one-sided p-value that KhGRL's is higher):", "",
            "| scenario | seeds (KhGRL/KGRL) | first success w/o human | stable success | zero obstacle cost from | "
            "success, last 10 |", "|---|---|---|---|---|---|"]
    from scipy.stats import mannwhitneyu

    for scenario in sorted({k[0] for k in groups}):
        a, b = groups.get((scenario, "khgrl")), groups.get((scenario, "kgrl"))
        if not a or not b:
            continue
        cells = []
        for attr in ("first_success_without_human", "stable_success", "zero_obstacle_cost_from"):
            va, vb = [getattr(r, attr) for r in a], [getattr(r, attr) for r in b]
            p = _compare(va, vb, episodes)
            cells.append(f"{median_text(va, episodes)} vs {median_text(vb, episodes)} (p = {p:.3f})")
        sa, sb = [r.success_last_10 for r in a], [r.success_last_10 for r in b]
        p = 1.0 if len(set(sa + sb)) == 1 else float(mannwhitneyu(sa, sb, alternative="greater").pvalue)
        cells.append(f"{np.mean(sa) - np.mean(sb):+.0%} (p = {p:.3f})")
        comp.append(f"| {scenario} | {len(a)}/{len(b)} | " + " | ".join(cells) + " |")
    return "\n".join(lines + comp) + "\n"
