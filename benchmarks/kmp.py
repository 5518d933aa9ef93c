"""Per-step LC-NS-KMP cost (``khgrl bench kmp``): what one control step of the actor costs.

Problem: the high-covariance passage world's 9 demonstrations, N = 400, O = 2, F = 4 box constraints
(the workspace [0.02, 0.98]^2). Cases, each timed as the median of repeated calls in one process:

* build: GMM/GMR excluded; the LCNSKMP constructor (Cholesky, tables, dual Hessian);
* grid step without constraints (tables: eta0_n + N_n xi);
* grid step with constraints that stay inactive (KKT shortcut: q >= 0);
* grid step with active constraints (xi pushes P_t through the workspace bound; warm-started active set
  along a sweep of consecutive steps), and the same without warm start (first step of an episode);
* the direct formula (general ``predict`` at s* = s_hat = s_n: Cholesky solves + dual QP);
* ``lc-ns-kmp`` 0.1.0's ``predict_LCNS`` on the same inputs, when installed (inactive / active);
* the via-point refit of a varying scene (:func:`khgrl.common.kmp.adapt.adapt_model`, what the actor does at every
  reset of such a task): the Fetch teacher's demonstrations at N = 100 and N = 400, O = 3, F = 6 (the workspace
  box), two via-points at the grasp.
"""

from __future__ import annotations

import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np
from khgrl.common.kmp.fit import KMPConfig, box_constraints, fit_model
from khgrl.common.tasks.passage.scenarios import make_demos

__all__ = ["run_kmp_benchmark"]


def _median_time(fn, repeats: int) -> float:
    times = []
    for k in range(repeats):
        t0 = time.perf_counter()
        fn(k)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _fmt(seconds: float) -> str:
    if seconds < 1e-3:
        return f"{seconds * 1e6:9.1f} µs"
    if seconds < 1.0:
        return f"{seconds * 1e3:9.2f} ms"
    return f"{seconds:9.2f} s "


def _refit_times(repeats: int = 5) -> dict[int, float]:
    """Median time of one via-point refit (``adapt_model``) of the Fetch task's KMP, by grid size N."""
    from khgrl.common.kmp.adapt import adapt_model
    from khgrl.common.tasks.fetch.task import DEMO_OBJECT, WORKSPACE, teacher_demos
    from khgrl.common.tasks.scene import ViaPoint

    G, c = box_constraints(*WORKSPACE)
    out = {}
    for n in (100, 400):
        model, _ = fit_model(teacher_demos(n=n), KMPConfig(), (G, c))
        via = [ViaPoint(p, DEMO_OBJECT + [0.05, -0.1, 0.0]) for p in (0.32, 0.42)]
        out[n] = _median_time(lambda _: adapt_model(model, via), repeats)
    return out


def run_kmp_benchmark(repeats: int = 2000, seed: int = 0, out: str | None = None) -> dict:
    from rich.console import Console
    from rich.table import Table

    if repeats < 20:  # the cold and direct cases time at least 20 calls from the same tables
        raise ValueError(f"repeats must be >= 20, got {repeats}")
    console = Console()
    rng = np.random.default_rng(seed)
    demos = make_demos("high_cov", seed=seed)
    config = KMPConfig(seed=seed)
    G, c = box_constraints([0.02, 0.02], [0.98, 0.98])
    cpu = platform.processor() or platform.machine()
    console.print(f"[bold]LC-NS-KMP per-step benchmark[/] N=400, O=2, F=4, repeats={repeats} ({cpu})")

    t0 = time.perf_counter()
    free, ref = fit_model(demos, config)
    t_fit_free = time.perf_counter() - t0
    t0 = time.perf_counter()
    boxed, _ = fit_model(demos, config, (G, c))
    t_fit_boxed = time.perf_counter() - t0
    from khgrl.common.kmp.kernels import RBF
    from khgrl.common.kmp.lcnskmp import LCNSKMP

    def build(_):
        LCNSKMP(ref.s, ref.mu, ref.sigma, lam=config.lam, beta=config.beta, kernel=RBF(config.length_scale),
                constraints=(G, c))

    t_build = _median_time(build, 5)

    n_grid = ref.s.shape[0]
    steps = rng.integers(0, n_grid, size=repeats)
    small = rng.uniform(-1, 1, size=(repeats, 2)) * 1.0  # L * a with L = 1: stays inside the box
    # Active: push y through the upper bound on a sweep of consecutive steps in the wide region
    sweep = np.arange(repeats) % 160 + 120
    push = np.stack([np.zeros(repeats), 80.0 + 20.0 * rng.uniform(size=repeats)], axis=1)

    results: dict[str, float] = {}
    results["grid step, no constraints"] = _median_time(lambda k: free.grid_step(int(steps[k]), small[k]), repeats)
    results["grid step, inactive constraints"] = _median_time(
        lambda k: boxed.grid_step(int(steps[k]), small[k]), repeats
    )
    active_counts = []

    def active_step(k):
        boxed.grid_step(int(sweep[k]), push[k])
        active_counts.append(boxed.step_info.active_rows)

    results["grid step, active constraints (warm)"] = _median_time(active_step, repeats)

    def cold_step(k):
        boxed._last_active = []
        boxed.grid_step(int(sweep[k]), push[k])

    results["grid step, active constraints (cold)"] = _median_time(cold_step, max(repeats // 10, 20))
    s = ref.s
    n_direct = max(repeats // 20, 20)
    results["direct formula, no constraints"] = _median_time(
        lambda k: free.predict(s[steps[k] : steps[k] + 1], small[k], s[steps[k]]), n_direct
    )
    results["direct formula, inactive constraints"] = _median_time(
        lambda k: boxed.predict(s[steps[k] : steps[k] + 1], small[k], s[steps[k]]), n_direct
    )
    results["direct formula, active constraints"] = _median_time(
        lambda k: boxed.predict(s[sweep[k] : sweep[k] + 1], push[k], s[sweep[k]]), n_direct
    )
    try:
        import lc_ns_kmp
    except ImportError:
        lc_ns_kmp = None
        console.print("lc-ns-kmp not installed: skipping its rows (pip install lc-ns-kmp==0.1.0)")
    if lc_ns_kmp is not None:
        ref_kmp = lc_ns_kmp.LC_NS_KMP(2, n_grid, config.lam, config.beta, RBF(config.length_scale).precision)
        ref_kmp.add_constraints(G, c[:, None])  # its QP enforces G eta >= c, like ours

        def lcns(k, xi, n):
            ref_kmp.predict_LCNS(s[n : n + 1], xi.reshape(2, 1), s[n].reshape(1, 1), s, ref.mu, ref.sigma)

        results["lc-ns-kmp predict_LCNS, inactive constraints"] = _median_time(
            lambda k: lcns(k, small[k], int(steps[k])), 3
        )
        results["lc-ns-kmp predict_LCNS, active constraints"] = _median_time(
            lambda k: lcns(k, push[k], int(sweep[k])), 3
        )

    table = Table(title="median time per call")
    table.add_column("case")
    table.add_column("time", justify="right")
    table.add_column("× grid step (same constraint case)", justify="right")
    base = {
        "no constraints": results["grid step, no constraints"],
        "inactive constraints": results["grid step, inactive constraints"],
        "active constraints": results["grid step, active constraints (warm)"],
    }
    table.add_row("build LCNSKMP (N=400, F=4)", _fmt(t_build), "")
    table.add_row("fit GMM/GMR + build, no constraints", _fmt(t_fit_free), "")
    table.add_row("fit GMM/GMR + build, box constraints", _fmt(t_fit_boxed), "")
    refits = _refit_times()
    for n, value in refits.items():
        table.add_row(f"via-point refit at reset (N={n}, O=3, F=6)", _fmt(value), "")
    for name, value in results.items():
        key = next((k for k in base if name.endswith(k) or f"{k} (" in name), None)
        ratio = f"{value / base[key]:,.0f}×" if key and not name.startswith("grid step") else ""
        table.add_row(name, _fmt(value), ratio)
    console.print(table)
    console.print(f"active-constraint sweep: {np.mean(active_counts):.1f} active rows on average "
                  f"(max {max(active_counts)})")
    record = {
        "config": config.to_dict(),
        "repeats": repeats,
        "seed": seed,
        "build_s": t_build,
        "refit_s": {str(n): v for n, v in refits.items()},
        "median_s": results,
        "active_rows_mean": float(np.mean(active_counts)),
        "machine": platform.platform(),
    }
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(record, indent=2))
        console.print(f"wrote {out}")
    return record
