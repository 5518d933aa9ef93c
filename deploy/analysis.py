"""Analysis of an experiment (``khgrl experiment`` output): statistics across seeds and Fig. 4-6 of the paper.

An experiment directory holds one run directory per (scenario, method, seed), named
``<scenario>-<method>-seed<S>`` (``khgrl up`` runs: ``actor-a0/episodes.csv``; ``khgrl reference`` runs:
``episodes.csv``). :func:`analyse` reads them all and writes, into an output directory:

* ``per_run.csv``      one row per run: the learning criteria below
* ``per_episode.csv``  per (scenario, method, episode) across seeds: mean, std, median, quartiles of return,
  obstacle cost and passage cost; success rate (the data behind the figures)
* ``scale.csv``        L over phase at the end of each run (Fig. 6 data)
* ``fig4_high_cov.png`` / ``fig5_low_cov.png``  return, obstacle cost, passage cost, success rate per episode
  (mean +- std band over seeds, human episodes shaded); ``fig6_scale.png`` L over phase
* ``summary.md``       the tables: per method and scenario, and KhGRL vs KGRL with a rank test

Learning criteria of one run (all in episodes, counted from 1; ``None`` = never within the run):

* first success; first success without human help (no intervention in that episode)
* **stable success**: the first episode of the first 5 consecutive *autonomous* episodes (no human
  intervention) that all succeed -- human-assisted episodes are skipped, neither counted nor breaking the run
* **zero obstacle cost**: the episode from which no later episode touches the obstacle (obstacle cost 0
  in that episode and every one after it)
* success rate over the last 10 episodes; episodes with a collision (obstacle cost < 0) during learning
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

__all__ = ["RunResult", "find_runs", "load_run", "stable_success", "zero_cost_from", "analyse", "STABLE_WINDOW"]

RUN_NAME = re.compile(r"^(?P<scenario>high_cov|low_cov)-(?P<method>khgrl|kgrl)-seed(?P<seed>\d+)$")
STABLE_WINDOW = 5  # consecutive autonomous successes that count as "stable success"
METHOD_LABEL = {"khgrl": "KhGRL", "kgrl": "KGRL"}
METHOD_COLOR = {"khgrl": "C3", "kgrl": "C0"}
FIGURE = {"high_cov": ("fig4_high_cov.png", "Fig. 4 (high-covariance scenario A)"),
          "low_cov": ("fig5_low_cov.png", "Fig. 5 (low-covariance scenario B)")}


@dataclass
class RunResult:
    scenario: str
    method: str
    seed: int
    path: str
    episodes: int
    successes: int
    success_last_10: float
    first_success: int | None
    first_success_without_human: int | None
    stable_success: int | None
    zero_obstacle_cost_from: int | None
    collision_episodes: int
    obstacle_steps: int
    human_episodes: int
    intervention_steps: int
    clipped_human_steps: int
    mean_return_last_10: float


def stable_success(success: list[bool], human: list[bool], window: int = STABLE_WINDOW) -> int | None:
    """First episode (1-based) of the first ``window`` consecutive autonomous successes; human episodes skipped."""
    run: list[int] = []
    for ep, (s, h) in enumerate(zip(success, human), start=1):
        if h:
            continue
        run = run + [ep] if s else []
        if len(run) == window:
            return run[0]
    return None


def zero_cost_from(costs: list[float]) -> int | None:
    """First episode (1-based) from which every episode's cost is 0; None if the last episode has a cost."""
    e = None
    for ep in range(len(costs), 0, -1):
        if costs[ep - 1] < 0:
            break
        e = ep
    return e


def find_runs(exp_dir: Path) -> list[tuple[str, str, int, Path]]:
    """(scenario, method, seed, run dir) of every run directory in ``exp_dir`` that has episode results."""
    out = []
    for d in sorted(Path(exp_dir).iterdir()):
        m = RUN_NAME.match(d.name)
        if m and d.is_dir() and _episodes_file(d) is not None:
            out.append((m["scenario"], m["method"], int(m["seed"]), d))
    return out


def _episodes_file(run_dir: Path) -> Path | None:
    for f in (run_dir / "episodes.csv", run_dir / "actor-a0" / "episodes.csv"):
        if f.exists():
            return f
    return None


def load_run(run_dir: Path) -> list[dict]:
    """Episode rows of a run, typed."""
    f = _episodes_file(run_dir)
    if f is None:
        raise FileNotFoundError(f"{run_dir}: no episodes.csv")
    with open(f, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return [{"episode": int(r["episode"]), "ret": float(r["ret"]), "success": r["success"] == "True",
             "obstacle_cost": float(r["obstacle_cost"]), "passage_cost": float(r["passage_cost"]),
             "obstacle_steps": int(r["obstacle_steps"]), "intervention_steps": int(r["intervention_steps"]),
             "clipped_steps": int(r["clipped_steps"])} for r in rows]


def summarize_run(scenario: str, method: str, seed: int, run_dir: Path, rows: list[dict]) -> RunResult:
    succ = [r["success"] for r in rows]
    human = [r["intervention_steps"] > 0 for r in rows]
    last = rows[-10:]
    return RunResult(
        scenario=scenario, method=method, seed=seed, path=str(run_dir), episodes=len(rows), successes=sum(succ),
        success_last_10=sum(r["success"] for r in last) / max(1, len(last)),
        first_success=next((r["episode"] for r in rows if r["success"]), None),
        first_success_without_human=next((r["episode"] for r, h in zip(rows, human) if r["success"] and not h), None),
        stable_success=stable_success(succ, human),
        zero_obstacle_cost_from=zero_cost_from([r["obstacle_cost"] for r in rows]),
        collision_episodes=sum(r["obstacle_cost"] < 0 for r in rows),
        obstacle_steps=sum(r["obstacle_steps"] for r in rows),
        human_episodes=sum(human), intervention_steps=sum(r["intervention_steps"] for r in rows),
        clipped_human_steps=sum(r["clipped_steps"] for r in rows),
        mean_return_last_10=float(np.mean([r["ret"] for r in last])) if last else float("nan"),
    )


def _matrix(runs: list[list[dict]], key: str, episodes: int) -> np.ndarray:
    """(seeds, episodes) of one per-episode quantity; NaN where a run is shorter."""
    m = np.full((len(runs), episodes), np.nan)
    for i, rows in enumerate(runs):
        for r in rows[:episodes]:
            m[i, r["episode"] - 1] = float(r[key])
    return m


def _censored(v: int | None, episodes: int) -> int:
    """'never within the run' ranks after every episode of the run."""
    return episodes + 1 if v is None else v


def _median_text(values: list[int | None], episodes: int) -> str:
    """Median over seeds with 'never' ranked last; a median between an episode and 'never' is shown as a range."""
    x = sorted(_censored(v, episodes) for v in values)
    lo, hi = x[(len(x) - 1) // 2], x[len(x) // 2]
    name = lambda v: "never" if v > episodes else f"{v:g}"  # noqa: E731
    if lo == hi or (lo <= episodes and hi <= episodes):
        return name((lo + hi) / 2)
    return f"{name(lo)}–{name(hi)}"


def _fmt_episode(values: list[int | None], episodes: int) -> str:
    """'median (per seed: ...)', seeds in order; 'never' = not within the run."""
    per_seed = ", ".join("never" if v is None else str(v) for v in values)
    return f"{_median_text(values, episodes)} ({per_seed})"


def _compare(a: list[int | None], b: list[int | None], episodes: int) -> float:
    """One-sided Mann-Whitney U p-value that the episodes in ``a`` come earlier than in ``b`` ('never' ranks last)."""
    from scipy.stats import mannwhitneyu

    xa = [_censored(v, episodes) for v in a]
    xb = [_censored(v, episodes) for v in b]
    if len(set(xa + xb)) == 1:
        return 1.0
    return float(mannwhitneyu(xa, xb, alternative="less").pvalue)


def _human_episodes(runs: list[list[dict]]) -> list[int]:
    eps = set()
    for rows in runs:
        eps |= {r["episode"] for r in rows if r["intervention_steps"] > 0}
    return sorted(eps)


def plot_learning(scenario: str, groups: dict[str, list[list[dict]]], episodes: int, path: Path, title: str) -> None:
    """Return, obstacle cost, passage cost and success rate per episode: mean +- std over seeds per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("ret", "return"), ("obstacle_cost", "obstacle cost"), ("passage_cost", "passage cost"),
            ("success", "success rate")]
    fig, axes = plt.subplots(len(keys), 1, figsize=(9, 10), sharex=True, constrained_layout=True)
    ep = np.arange(1, episodes + 1)
    for method, runs in groups.items():
        color, label = METHOD_COLOR[method], f"{METHOD_LABEL[method]} ({len(runs)} seeds)"
        for ax, (key, _) in zip(axes, keys):
            m = _matrix(runs, key, episodes)
            mean = np.nanmean(m, axis=0)
            ax.plot(ep, mean, color=color, label=label, lw=1.6)
            if key != "success":
                std = np.nanstd(m, axis=0)
                ax.fill_between(ep, mean - std, mean + std, color=color, alpha=0.18, lw=0)
        if method == "khgrl":
            for h in _human_episodes(runs):
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


def load_scale(run_dir: Path, scenario: str) -> tuple[np.ndarray, np.ndarray, bool]:
    """(phases (N,), L (N, O), recorded) at the end of a run. Runs without a recorded table (single-process
    reference KGRL, or runs made before the actor wrote ``scale.npz``) never refit L: the scenario's default."""
    from common.scenarios import get_scenario

    f = run_dir / "actor-a0" / "scale.npz"
    if f.exists():
        d = np.load(f)
        return d["phases"], d["table"], True
    if (run_dir / "scale_table.npy").exists():
        table = np.load(run_dir / "scale_table.npy")
        return np.linspace(0.0, 1.0, table.shape[0]), table, True
    sc = get_scenario(scenario)
    n = 400
    return np.linspace(0.0, 1.0, n), np.full((n, 2), sc.default_scale), False


def _corrected_phases(run_dir: Path, n: int) -> np.ndarray:
    f = run_dir / "actor-a0" / "corrections.csv"
    if not f.exists():
        return np.zeros(0)
    with open(f, newline="") as fh:
        steps = [int(r["step"]) for r in csv.DictReader(fh)]
    return np.asarray(steps, dtype=np.float64) / (n - 1)


def plot_scale(scales: dict, path: Path) -> None:
    """Fig. 6: L_x and L_y over phase at the end of each run, per scenario; where the human intervened, shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = sorted({k[0] for k in scales})
    fig, axes = plt.subplots(len(scenarios), 2, figsize=(11, 3.6 * len(scenarios)), squeeze=False, constrained_layout=True)
    for row, scenario in enumerate(scenarios):
        for (sc, method), items in sorted(scales.items()):
            if sc != scenario:
                continue
            for i, (phases, table, corrected) in enumerate(items):
                for d, ax in enumerate(axes[row]):
                    ax.plot(phases, table[:, d], color=METHOD_COLOR[method], lw=1.0, alpha=0.8,
                            label=f"{METHOD_LABEL[method]} ({len(items)} seeds)" if i == 0 else None)
                    if method == "khgrl" and corrected.size:
                        ax.axvspan(corrected.min(), corrected.max(), color="0.9", zorder=0, lw=0)
        from common.scenarios import get_scenario

        note = "grey: phases the human corrected" + ("" if get_scenario(scenario).learn_scale
                                                      else "; L is not learned here, as in the paper")
        for d, ax in enumerate(axes[row]):
            ax.set_title(f"{scenario}: L_{'xy'[d]} at the end of each run ({note})", fontsize=9)
            ax.set_xlabel("phase s")
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
        axes[row][0].legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def analyse(exp_dirs: list[Path], out: Path, seeds: list[int] | None = None, scenarios: list[str] | None = None) -> str:
    """Read every run of the experiment directories (optionally only some seeds / scenarios), write the tables and
    figures into ``out``; return summary.md."""
    found = [r for d in exp_dirs for r in find_runs(Path(d))
             if (seeds is None or r[2] in seeds) and (scenarios is None or r[0] in scenarios)]
    if not found:
        raise FileNotFoundError(f"no run directories named <scenario>-<method>-seed<S> with results in {exp_dirs}")
    out.mkdir(parents=True, exist_ok=True)
    data: dict[tuple[str, str], list[list[dict]]] = {}
    results: list[RunResult] = []
    scales: dict[tuple[str, str], list] = {}
    for scenario, method, seed, run_dir in found:
        rows = load_run(run_dir)
        data.setdefault((scenario, method), []).append(rows)
        results.append(summarize_run(scenario, method, seed, run_dir, rows))
        phases, table, _ = load_scale(run_dir, scenario)
        scales.setdefault((scenario, method), []).append((phases, table, _corrected_phases(run_dir, len(phases))))
    episodes = max(len(rows) for runs in data.values() for rows in runs)

    with open(out / "per_run.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(asdict(results[0])))
        w.writeheader()
        w.writerows(asdict(r) for r in results)
    _write_per_episode(data, episodes, out / "per_episode.csv")
    _write_scale(found, scales, out / "scale.csv")
    for scenario in sorted({k[0] for k in data}):
        name, title = FIGURE[scenario]
        groups = {m: data[(scenario, m)] for m in ("khgrl", "kgrl") if (scenario, m) in data}
        plot_learning(scenario, groups, episodes, out / name, title)
    plot_scale(scales, out / "fig6_scale.png")
    text = summary_markdown(results, episodes)
    (out / "summary.md").write_text(text)
    return text


def _write_per_episode(data: dict, episodes: int, path: Path) -> None:
    keys = ("ret", "obstacle_cost", "passage_cost")
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        head = ["scenario", "method", "episode", "seeds"]
        for k in keys:
            head += [f"{k}_{s}" for s in ("mean", "std", "median", "q25", "q75")]
        w.writerow(head + ["success_rate", "human_seeds"])
        for (scenario, method), runs in sorted(data.items()):
            mats = {k: _matrix(runs, k, episodes) for k in (*keys, "success", "intervention_steps")}
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
        w.writerow(["scenario", "method", "seed", "phase", "L_x", "L_y"])
        index: dict[tuple[str, str], int] = {}
        for scenario, method, seed, _ in found:
            i = index.get((scenario, method), 0)
            index[(scenario, method)] = i + 1
            phases, table, _ = scales[(scenario, method)][i]
            for p, (lx, ly) in zip(phases, table):
                w.writerow([scenario, method, seed, f"{p:.5f}", f"{lx:.6g}", f"{ly:.6g}"])


def summary_markdown(results: list[RunResult], episodes: int) -> str:
    groups: dict[tuple[str, str], list[RunResult]] = {}
    for r in results:
        groups.setdefault((r.scenario, r.method), []).append(r)
    cols = ["scenario", "method", "seeds", "success, last 10 (mean ± std; per seed)", "first success",
            "first success w/o human", f"stable success ({STABLE_WINDOW} in a row)", "zero obstacle cost from",
            "collision episodes", "human episodes", "clipped / human steps", "return, last 10"]
    lines = [f"Episodes per run: {episodes}. Episode criteria: median over seeds ('never' = not within the run, ranked "
             "last; a median between an episode and 'never' is shown as a range), then each seed's value in seed order.",
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
            f"{_fmt_episode([r.first_success for r in rs], episodes)} | "
            f"{_fmt_episode([r.first_success_without_human for r in rs], episodes)} | "
            f"{_fmt_episode([r.stable_success for r in rs], episodes)} | "
            f"{_fmt_episode([r.zero_obstacle_cost_from for r in rs], episodes)} | "
            f"{np.mean([r.collision_episodes for r in rs]):.1f} ({', '.join(str(r.collision_episodes) for r in rs)}) | "
            f"{np.mean([r.human_episodes for r in rs]):.1f} | "
            f"{sum(r.clipped_human_steps for r in rs)} / {iv} | "
            f"{np.mean([r.mean_return_last_10 for r in rs]):.1f} ± {np.std([r.mean_return_last_10 for r in rs]):.1f} |")
    comp = ["", "KhGRL vs KGRL (episode criteria: median KhGRL vs median KGRL over seeds, 'never' ranked last, and "
                "the one-sided Mann–Whitney U p-value that KhGRL's episodes come earlier; success rate over the last 10: "
                "mean KhGRL − mean KGRL and the one-sided p-value that KhGRL's is higher):", "",
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
            cells.append(f"{_median_text(va, episodes)} vs {_median_text(vb, episodes)} (p = {p:.3f})")
        sa, sb = [r.success_last_10 for r in a], [r.success_last_10 for r in b]
        p = 1.0 if len(set(sa + sb)) == 1 else float(mannwhitneyu(sa, sb, alternative="greater").pvalue)
        cells.append(f"{np.mean(sa) - np.mean(sb):+.0%} (p = {p:.3f})")
        comp.append(f"| {scenario} | {len(a)}/{len(b)} | " + " | ".join(cells) + " |")
    return "\n".join(lines + comp) + "\n"


def experiment_config(exp_dir: Path) -> dict | None:
    """The experiment's recorded configuration and run statuses, if it was made by ``khgrl experiment``."""
    f = Path(exp_dir) / "experiment.json"
    return json.loads(f.read_text()) if f.exists() else None
