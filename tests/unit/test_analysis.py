"""khgrl.deploy.experiments.analysis: the learning criteria, the cross-seed tables and figures of ``khgrl
report EXP``."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from khgrl.deploy.experiments.analysis import analyse, find_runs, stable_success, zero_cost_from

FIELDS = ["episode", "steps", "ret", "success", "failure", "action_cost", "obstacle_cost", "passage_cost",
          "obstacle_steps", "interventions", "intervention_steps", "clipped_steps", "projected_steps", "mean_abs_xi_h",
          "scale_max", "wall_time"]


def test_stable_success_skips_human_episodes():
    s = [False, True, True, True, True, False, True, True, True, True, True]
    h = [False] * len(s)
    assert stable_success(s, h) == 7  # 2-5 is only four in a row
    h2 = list(h)
    h2[5] = True  # the failure at 6 had human help: skipped, 2-5 and 7 make five autonomous successes
    assert stable_success(s, h2) == 2
    assert stable_success([True] * 4, [False] * 4) is None
    # human-assisted successes do not count towards the window
    assert stable_success([True] * 6, [True, True, False, False, False, False]) is None


def test_zero_cost_from():
    assert zero_cost_from([0, -5, 0, 0]) == 3
    assert zero_cost_from([0, 0, 0]) == 1
    assert zero_cost_from([0, 0, -1]) is None
    assert zero_cost_from([]) is None


def _write_run(
    path: Path, success: list[bool], obstacle: list[float], human: set[int] = frozenset(), actor: bool = True
) -> None:
    d = path / "actor-a0" if actor else path
    d.mkdir(parents=True)
    with open(d / "episodes.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        for i, (s, o) in enumerate(zip(success, obstacle), start=1):
            iv = 10 if i in human else 0
            w.writerow({"episode": i, "steps": 100, "ret": (180.0 if s else -200.0) + o, "success": str(s),
                        "failure": str(not s), "action_cost": -1.0, "obstacle_cost": o,
                        "passage_cost": 0.0 if s else -200.0,
                        "obstacle_steps": int(-o / 10), "interventions": int(iv > 0), "intervention_steps": iv,
                        "clipped_steps": iv // 2, "projected_steps": 0, "mean_abs_xi_h": 0.0, "scale_max": "15;15",
                        "wall_time": 1.0})


def test_analyse_writes_tables_and_figures(tmp_path):
    exp = tmp_path / "exp"
    n = 12
    # KhGRL: succeeds from episode 3 (seed 0) / 5 (seed 1), human at 2; KGRL never, one collision at 7 in seed 0
    _write_run(exp / "low_cov-khgrl-seed0", [False, True] + [True] * 10, [0.0] * n, human={2})
    _write_run(exp / "low_cov-khgrl-seed1", [False] * 4 + [True] * 8, [-30.0] + [0.0] * 11, human={2})
    _write_run(exp / "low_cov-kgrl-seed0", [False] * n, [0.0] * 6 + [-20.0] + [0.0] * 5)
    _write_run(exp / "low_cov-kgrl-seed1", [False] * n, [0.0] * n, actor=False)  # a reference-style run dir
    (exp / "notes").mkdir()  # not a run: ignored
    (exp / "high_cov-kgrl-seed9").mkdir()  # a run without results yet: ignored
    assert [r[:3] for r in find_runs(exp)] == [("low_cov", "kgrl", 0), ("low_cov", "kgrl", 1),
                                              ("low_cov", "khgrl", 0), ("low_cov", "khgrl", 1)]
    out = tmp_path / "report"
    text = analyse([exp], out)
    for f in ("per_run.csv", "per_episode.csv", "scale.csv", "summary.md", "fig5_low_cov.png", "fig6_scale.png"):
        assert (out / f).stat().st_size > 0, f
    assert not (out / "fig4_high_cov.png").exists()
    runs = {(r["method"], r["seed"]): r for r in csv.DictReader(open(out / "per_run.csv"))}
    k0, k1, g0 = runs[("khgrl", "0")], runs[("khgrl", "1")], runs[("kgrl", "0")]
    assert (k0["first_success"], k0["first_success_without_human"], k0["stable_success"]) == ("2", "3", "3")
    assert (k1["first_success"], k1["stable_success"], k1["zero_obstacle_cost_from"]) == ("5", "5", "2")
    assert (g0["first_success"], g0["stable_success"], g0["zero_obstacle_cost_from"]) == ("", "", "8")
    assert k0["human_episodes"] == "1" and k0["clipped_human_steps"] == "5" and float(k0["success_last_10"]) == 1.0
    assert g0["collision_episodes"] == "1"
    # per-episode statistics: episode 1 return of KhGRL is the mean of -200 and -230
    rows = [r for r in csv.DictReader(open(out / "per_episode.csv")) if r["method"] == "khgrl"]
    assert float(rows[0]["ret_mean"]) == pytest.approx(-215.0) and float(rows[0]["ret_std"]) == pytest.approx(15.0)
    assert float(rows[3]["success_rate"]) == pytest.approx(0.5) and rows[1]["human_seeds"] == "2"
    # without a recorded scale table, L is the scenario's constant default
    scale = [r for r in csv.DictReader(open(out / "scale.csv")) if r["method"] == "kgrl"]
    assert {float(r["L_x"]) for r in scale} == {15.0}
    assert "| low_cov | KhGRL | 0, 1 | 90% ± 10% (100%, 80%)" in text and "| low_cov | 2/2 |" in text
    assert "| never (never, never) |" in text  # KGRL never succeeds, on either seed
    assert "| 3.5 (2, 5) |" in text  # KhGRL's first success: median of seeds 0 and 1, then each seed's
    assert "| 4 vs never (p = " in text  # first success without human help: KhGRL (3, 5) vs KGRL (never, never)


def test_report_cli_dispatches_and_rejects_mixed_input(tmp_path, capsys):
    from khgrl.deploy.experiments.report import main

    exp = tmp_path / "exp"
    _write_run(exp / "high_cov-kgrl-seed0", [False, True], [0.0, 0.0])
    single = tmp_path / "single"
    _write_run(single, [True], [0.0], actor=False)
    assert main([str(exp)]) == 0 and (exp / "report" / "fig4_high_cov.png").exists()
    assert main([str(single), "--out", str(tmp_path / "one.png")]) == 0 and (tmp_path / "one.md").exists()
    assert main([str(exp), "--seeds", "0", "--out", str(tmp_path / "r0")]) == 0
    assert main([str(exp), "--seeds", "5", "--out", str(tmp_path / "r5")]) == 2  # nothing left to analyse
    assert main([str(exp), str(single)]) == 2
    assert main([str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert "not both" in err and "not a directory" in err and "no run directories" in err
    # --with-report: an earlier report's directory, never the one written, and only beside experiments
    assert main([str(exp), "--with-report", str(tmp_path)]) == 2 and "no convergence.csv" in capsys.readouterr().err
    (tmp_path / "r0" / "convergence.csv").write_text("task,method\nfetch_moved,khgrl\n")
    assert main([str(exp), "--with-report", str(tmp_path / "r0"), "--out", str(tmp_path / "r0")]) == 2
    assert "would be overwritten" in capsys.readouterr().err and (tmp_path / "r0" / "summary.md").exists()
    assert main([str(exp), "--with-report", str(tmp_path / "r0"), "--out", str(tmp_path / "r1")]) == 2
    assert "line 2: not a convergence.csv row" in capsys.readouterr().err
    assert main([str(single), "--with-report", str(tmp_path / "r0")]) == 2
    assert "give experiment directories" in capsys.readouterr().err
    assert np.isfinite(float(next(csv.DictReader(open(exp / "report" / "per_run.csv")))["mean_return_last_10"]))


def test_task_runs_report_every_output_and_the_evaluation(tmp_path):
    """Runs of a task (``khgrl experiment --tasks``): a 3-output scale table, no obstacle columns where no run has an
    obstacle, and the success of ``khgrl eval`` where the runs were evaluated."""
    exp = tmp_path / "exp"
    n = 12
    for method, seed, succ in [("khgrl", 0, [True] * n), ("khgrl", 1, [False] * 6 + [True] * 6),
                               ("kgrl", 0, [False] * n), ("kgrl", 1, [False] * n)]:
        run = exp / f"fetch_moved-{method}-seed{seed}"
        _write_run(run, succ, [0.0] * n, human={4} if method == "khgrl" else frozenset())
        table = np.full((50, 3), 5.0)
        table[15:25, 1] = 900.0 if method == "khgrl" else 5.0
        np.savez(run / "actor-a0" / "scale.npz", phases=np.linspace(0, 1, 50), table=table)
        (run / "eval").mkdir()
        with open(run / "eval" / "eval.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["episode", "seed", "steps", "return", "env_return", "action_cost", "success", "terminated"])
            for e in range(4):
                w.writerow([e + 1, e, 100, 0.0, 0.0, 0.0, method == "khgrl" and (seed == 0 or e < 2), False])
    out = tmp_path / "report"
    text = analyse([exp], out)
    assert (out / "learning_fetch_moved.png").stat().st_size > 0 and (out / "fig6_scale.png").stat().st_size > 0
    scale = list(csv.DictReader(open(out / "scale.csv")))
    assert {"L_x", "L_y", "L_z"} <= set(scale[0]) and max(float(r["L_y"]) for r in scale) == 900.0
    assert "obstacle" not in text and "collision" not in text
    assert "| 75% (100%, 50%; 4 episodes) |" in text and "| 0% (0%, 0%; 4 episodes) |" in text
    assert "+75% (p = " in text  # KhGRL's eval success above KGRL's
    runs = {(r["method"], r["seed"]): r for r in csv.DictReader(open(out / "per_run.csv"))}
    assert (runs[("khgrl", "1")]["eval_success"], runs[("khgrl", "1")]["eval_episodes"]) == ("0.5", "4")


def test_median_over_seeds_with_never():
    from khgrl.deploy.experiments.summary_table import fmt_episode, median_text

    assert median_text([3, 5, None], 60) == "5"
    assert median_text([None, None, 22, 2], 60) == "22–never"  # between an episode and 'never': a range
    assert median_text([None, None], 60) == "never"
    assert median_text([2, 5], 60) == "3.5"
    assert fmt_episode([None, 7], 60) == "7–never (never, 7)"


def test_report_compares_with_hil_serl_in_human_steps_and_counts_safety(tmp_path):
    """Runs of the issue-23 methods: the budget, safety and compute columns, and the comparison of the human steps
    spent before the first autonomous success (old episodes.csv files without the new columns read as 0)."""
    exp = tmp_path / "exp"
    n = 12
    for seed in (0, 1, 2):
        _write_run(exp / f"low_cov-khgrl-seed{seed}", [False, True, False] + [True] * 9, [0.0] * n, human={2})
        _write_run(exp / f"low_cov-hil-serl-seed{seed}", [False] * n, [0.0] * n, human={2})
        _write_run(exp / f"low_cov-khgrl_rlpd-seed{seed}", [False, True] + [True] * 10, [0.0] * n, human={2})
    assert {m for _, m, _, _ in find_runs(exp)} == {"khgrl", "hil-serl", "khgrl_rlpd"}
    text = analyse([exp], tmp_path / "out")
    assert "human steps before first autonomous success" in text and "hard-constraint violation steps" in text
    khgrl_vs_hil = next(line for line in text.splitlines() if line.startswith("| low_cov | 3/3 |"))
    # KhGRL: 10 human steps (episode 2) before its first autonomous success (3 or 4); HIL-SERL never succeeds
    assert "| 10 vs never (p = 0.023) |" in khgrl_vs_hil, khgrl_vs_hil  # (scipy: asymptotic, ties within groups)


def test_runs_the_experiment_still_runs_are_left_out_and_named(tmp_path):
    """``khgrl report`` during an experiment: a run that experiment.json says is running (or was interrupted) is
    not a result yet -- left out of every table and named under the summary."""
    import json

    exp = tmp_path / "exp"
    _write_run(exp / "high_cov-kgrl-seed0", [False, True], [0.0, 0.0])
    _write_run(exp / "high_cov-kgrl-seed1", [True], [0.0])
    (exp / "experiment.json").write_text(json.dumps({"runs": {"high_cov-kgrl-seed0": {"status": "done"},
                                                              "high_cov-kgrl-seed1": {"status": "running"}}}))
    text = analyse([exp], tmp_path / "out")
    with open(tmp_path / "out" / "per_run.csv", newline="") as fh:
        assert [r["seed"] for r in csv.DictReader(fh)] == ["0"]
    assert "Left out, not finished" in text and "high_cov-kgrl-seed1" in text and "seed0" not in text.split("Left")[1]
