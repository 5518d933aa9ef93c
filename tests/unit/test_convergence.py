"""khgrl.deploy.experiments.convergence: milestones, human budget, HIL-SERL : KhGRL ratios and the files of
``khgrl report EXP`` for a task's runs of several methods."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from khgrl.deploy.experiments.analysis import analyse
from khgrl.deploy.experiments.convergence import (
    milestone_episode,
    ratio_interval,
    run_convergence,
    smallest_p,
    write_convergence,
)
from khgrl.deploy.experiments.run_milestones import load_report_runs
from khgrl.deploy.experiments.run_results import find_runs
from khgrl.deploy.tools.intervals import wilson_interval

FIELDS = ["episode", "steps", "ret", "success", "failure", "action_cost", "obstacle_cost", "passage_cost",
          "obstacle_steps", "interventions", "intervention_steps", "clipped_steps", "projected_steps", "mean_abs_xi_h",
          "scale_max", "wall_time"]
TEACHER = {"tries": 22, "kept": 20, "steps": 280, "steps_driven": 300, "box": None}


def _write_run(path: Path, success: list[bool], human: dict[int, int], teacher: dict | None = None,
               converged: bool = False, evaluated: tuple[int, int] | None = None) -> None:
    """A run directory: ``human`` {episode: intervention steps}; each episode 100 steps, 0.5 s."""
    d = path / "actor-a0"
    d.mkdir(parents=True)
    with open(d / "episodes.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        for i, s in enumerate(success, start=1):
            iv = human.get(i, 0)
            w.writerow({"episode": i, "steps": 100, "ret": 1.0 if s else -1.0, "success": str(s), "failure": "False",
                        "action_cost": 0.0, "obstacle_cost": 0.0, "passage_cost": 0.0, "obstacle_steps": 0,
                        "interventions": int(iv > 0), "intervention_steps": iv, "clipped_steps": 0,
                        "projected_steps": 0, "mean_abs_xi_h": 0.0, "scale_max": "1;1;1", "wall_time": 0.5})
    (d / "summary.json").write_text(json.dumps({"teacher": teacher, "converged": converged}))
    np.savez(d / "scale.npz", phases=np.linspace(0, 1, 5), table=np.ones((5, 3)))
    if evaluated is not None:
        (path / "eval").mkdir()
        with open(path / "eval" / "eval.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["episode", "seed", "steps", "return", "env_return", "action_cost", "success", "terminated"])
            for e in range(evaluated[1]):
                w.writerow([e + 1, e, 100, 0.0, 0.0, 0.0, e < evaluated[0], False])


# KhGRL seed 0: 25 episodes; human help at 2 (10 steps, a success: not autonomous) and 10 (5 steps); autonomous
# failures at 1, 4, 5, 6 and 13. First autonomous success: 3. Autonomous episodes a1..: 1, 3, 4, ..., 9, 11, 12, ...
# (a_k = episode k + 2 from a9); a1..a20 hold 5 failures, a2..a21 (episode 23) 4: 80/20 at episode 23.
KH0 = [i not in (1, 4, 5, 6, 13) for i in range(1, 26)]
KH0_HUMAN = {2: 10, 10: 5}


def _experiment(exp: Path) -> None:
    _write_run(exp / "fetch_moved-khgrl-seed0", KH0, KH0_HUMAN, evaluated=(9, 10))
    _write_run(exp / "fetch_moved-khgrl-seed1", [True] * 20, {}, converged=True, evaluated=(5, 10))
    # the recipe: 300 teacher steps; seed 0 never succeeds autonomously (its success at 5 had help), seed 1 at 2
    _write_run(exp / "fetch_moved-hil-serl_recipe-seed0", [i == 5 for i in range(1, 11)], {5: 20}, TEACHER,
               evaluated=(1, 10))
    _write_run(exp / "fetch_moved-hil-serl_recipe-seed1", [i == 2 for i in range(1, 9)], {}, TEACHER,
               evaluated=(0, 10))


def test_milestone_episode_skips_human_episodes():
    assert milestone_episode(KH0, [i in KH0_HUMAN for i in range(1, 26)], "first") == 3
    assert milestone_episode(KH0, [i in KH0_HUMAN for i in range(1, 26)], "80/20") == 23
    assert milestone_episode(KH0, [False] * 25, "first") == 2  # episode 2 counted if it were autonomous
    assert milestone_episode(KH0, [False] * 25, "80/20") == 21
    assert milestone_episode([True] * 19, [False] * 19, "80/20") is None  # no window of 20 yet
    assert milestone_episode([False] * 4 + [True] * 16, [False] * 20, "80/20") == 20  # 16/20 = 80 % is enough
    assert milestone_episode([False] * 5 + [True] * 15, [False] * 20, "80/20") is None


def test_run_milestones_human_budget_and_censoring(tmp_path):
    _experiment(tmp_path)
    kh = run_convergence("fetch_moved", "khgrl", 0, tmp_path / "fetch_moved-khgrl-seed0")
    first, window = kh.milestones["first"], kh.milestones["80/20"]
    assert (first.reached, first.episodes, first.steps, first.human_steps, first.wall_s) == (True, 3, 300, 10, 1.5)
    assert (window.reached, window.episodes, window.steps, window.human_steps, window.wall_s) == (
        True, 23, 2300, 15, 11.5)
    assert (kh.teacher_steps, kh.human_budget, kh.converged) == (0, 15, False)
    rec = run_convergence("fetch_moved", "hil-serl_recipe", 0, tmp_path / "fetch_moved-hil-serl_recipe-seed0")
    for m in rec.milestones.values():  # censored: the run's totals, the teacher's steps included
        assert (m.reached, m.episodes, m.steps, m.human_steps, m.wall_s) == (False, 10, 1000, 320, 5.0)
    assert (rec.teacher_steps, rec.human_budget) == (300, 320)
    rec1 = run_convergence("fetch_moved", "hil-serl_recipe", 1, tmp_path / "fetch_moved-hil-serl_recipe-seed1")
    assert (rec1.milestones["first"].reached, rec1.milestones["first"].human_steps) == (True, 300)
    assert run_convergence("fetch_moved", "khgrl", 1, tmp_path / "fetch_moved-khgrl-seed1").converged is True


def test_bootstrap_ratio_interval():
    hil, kh = [10.0, 20.0, 30.0, 40.0], [5.0, 5.0, 10.0]
    point, lo, hi = ratio_interval(hil, kh)
    assert point == pytest.approx(25.0 / (20.0 / 3.0))
    assert lo < point < hi
    assert ratio_interval(hil, kh) == (point, lo, hi)  # a fixed seed: the same interval
    assert 10.0 / 10.0 <= lo and hi <= 40.0 / 5.0  # within the most extreme resamples
    narrow = ratio_interval([24.0, 25.0, 26.0, 25.0], kh)  # less spread in one arm: a narrower interval
    assert narrow[0] == pytest.approx(point) and narrow[2] - narrow[1] < hi - lo
    assert ratio_interval([3.0, 3.0], [1.0, 1.0]) == (3.0, 3.0, 3.0)  # no spread, no interval


def test_wilson_and_smallest_p():
    low, high = wilson_interval(14, 20)
    assert (low, high) == pytest.approx((0.4810, 0.8545), abs=1e-4)
    assert smallest_p(5, 5) == pytest.approx(1 / 252)
    assert smallest_p(3, 2) == pytest.approx(1 / 10)


def test_report_writes_convergence_files(tmp_path):
    exp, out = tmp_path / "exp", tmp_path / "report"
    _experiment(exp)
    analyse([exp], out)
    for f in ("convergence.md", "convergence.csv", "curves_fetch_moved.png", "summary.md", "per_run.csv"):
        assert (out / f).stat().st_size > 0, f
    rows = {(r["method"], r["seed"], r["milestone"]): r for r in csv.DictReader(open(out / "convergence.csv"))}
    assert len(rows) == 8
    r = rows[("khgrl", "0", "80/20")]
    assert (r["reached"], r["episodes"], r["steps"], r["human_steps"], r["run_human_steps"]) == (
        "True", "23", "2300", "15", "15")
    r = rows[("hil-serl_recipe", "0", "first")]
    assert (r["reached"], r["episodes"], r["human_steps"], r["teacher_steps"]) == ("False", "10", "320", "300")
    text = (out / "convergence.md").read_text()
    lines = text.splitlines()
    # first autonomous success in episodes: recipe (>10, 2) mean 6 vs KhGRL (3, 1) mean 2: at least 3 times
    first = next(line for line in lines if line.startswith("| HIL-SERL, its recipe : KhGRL | first |"))
    assert first.split(" | ")[2].startswith("≥ 3 ["), first
    # 80/20: no recipe run reached it: (10 + 8) / 2 = 9 vs KhGRL (23 + 20) / 2 = 21.5; human steps (320 + 300) / 2
    # vs (15 + 0) / 2
    window = next(line for line in lines if line.startswith("| HIL-SERL, its recipe : KhGRL | 80/20 |"))
    assert window.split(" | ")[2] == "> 0.419", window
    assert window.split(" | ")[4] == "> 41.3" and window.endswith("| 0.167 |")  # 2 vs 2 seeds: 1 / C(4, 2)
    assert "| KhGRL | 14/20 = 70 % (95 % CI 48-85 %, Wilson) | episodes |" in text  # pooled over seeds 9/10, 5/10
    assert "| HIL-SERL, its recipe | 1/20 = 5 %" in text
    assert "| KhGRL | 80/20 | 21.5 (23, 20) |" in text and "| HIL-SERL, its recipe | 80/20 | ≥ 9 (>10, >8) |" in text
    # each run on its own line: seed 0 of KhGRL reached 80/20 without stopping there; the recipe's seed 0 never
    # succeeded on its own (its one success had help) and spent 300 teacher + 20 takeover steps
    assert "| KhGRL | 0 | 3 / 10 | episode 23 | 18 of 23 |" in lines
    assert "| KhGRL | 1 | 1 / 0 | episode 20 (ended there) | 20 of 20 |" in lines
    assert "| HIL-SERL, its recipe | 0 | none in 10 / 320 spent | not reached in 10; 0 of its last 9 autonomous " \
           "succeeded | 0 of 9 |" in lines
    assert "| HIL-SERL, its recipe | 1 | 2 / 300 (300 of them the teacher's) | not reached in 8; 1 of its last 8 " \
           "autonomous succeeded | 1 of 8 |" in lines


def test_the_recipe_against_the_protocol_once_both_hil_serl_arms_ran(tmp_path):
    exp, out = tmp_path / "exp", tmp_path / "report"
    _experiment(exp)
    assert "| HIL-SERL's recipe : its protocol |" not in write_convergence(find_runs(exp), out)  # (no protocol runs)
    # the protocol (no teacher): seed 0's first autonomous success at 8 of 10, seed 1 none in 10
    _write_run(exp / "fetch_moved-hil-serl-seed0", [i == 8 for i in range(1, 11)], {4: 12})
    _write_run(exp / "fetch_moved-hil-serl-seed1", [False] * 10, {4: 10})
    lines = write_convergence(find_runs(exp), out).splitlines()
    assert "| HIL-SERL's recipe : its protocol | milestone | episodes | env steps | human steps | wall s | min p |" \
        in lines
    # episodes to the first: recipe (>10, 2) mean 6 vs protocol (8, >10) mean 9; both have a censored run
    first = next(line for line in lines if line.startswith("| HIL-SERL, its recipe : HIL-SERL | first |"))
    assert first.split(" | ")[2].startswith("≥ 0.667 [") and first.split(" | ")[2].endswith("]†"), first
    # the whole run's human steps: recipe (320, 300) vs protocol (12, 10), never censored
    whole = next(line for line in lines if line.startswith("| HIL-SERL, its recipe : HIL-SERL | whole run |"))
    assert whole.split(" | ")[4].startswith("28.2 [") and whole.endswith("| 0.167 |"), whole


def test_no_convergence_files_for_one_method_or_a_passage_scenario(tmp_path):
    exp = tmp_path / "exp"
    _write_run(exp / "fetch_moved-khgrl-seed0", KH0, KH0_HUMAN)
    _write_run(exp / "low_cov-khgrl-seed0", KH0, KH0_HUMAN)
    _write_run(exp / "low_cov-hil-serl-seed0", KH0, {})
    assert write_convergence(find_runs(exp), tmp_path / "out") is None
    assert not (tmp_path / "out" / "convergence.md").exists()


def _tables(text: str) -> list[str]:
    """convergence.md without its header (the note and the line naming earlier reports)."""
    lines = text.splitlines()
    return lines[lines.index("## fetch_moved"):]


def test_an_earlier_reports_runs_join_the_tables_as_if_their_directories_were_at_hand(tmp_path):
    whole, part, later = tmp_path / "whole", tmp_path / "part", tmp_path / "later"
    _experiment(whole)
    analyse([whole], tmp_path / "r_whole")
    # the same four runs, three in one experiment (its report kept) and the recipe's seed 1 in another
    _experiment(part)
    (part / "fetch_moved-hil-serl_recipe-seed1").rename(tmp_path / "moved")
    later.mkdir()
    (tmp_path / "moved").rename(later / "fetch_moved-hil-serl_recipe-seed1")
    analyse([part], tmp_path / "r_part")
    analyse([later], tmp_path / "r_merged", earlier=[tmp_path / "r_part"])
    expected = (tmp_path / "r_whole" / "convergence.md").read_text()
    merged = (tmp_path / "r_merged" / "convergence.md").read_text()
    assert _tables(merged) == _tables(expected)  # ratios, per-run lines, evaluations: all as if at hand
    assert f"{tmp_path / 'r_part'}: 3 runs" in merged
    assert sorted(csv.DictReader(open(tmp_path / "r_merged" / "convergence.csv")), key=str) == \
        sorted(csv.DictReader(open(tmp_path / "r_whole" / "convergence.csv")), key=str)
    # a run in both: the one at hand counts (here a recipe seed 0 that succeeds at once, not the report's)
    _write_run(later / "fetch_moved-hil-serl_recipe-seed0", [True] * 3, {}, TEACHER)
    lines = write_convergence(find_runs(later), tmp_path / "r2", load_report_runs(tmp_path / "r_part")).splitlines()
    assert "| HIL-SERL, its recipe | 0 | 1 / 300 (300 of them the teacher's) | not reached in 3; 3 of its last 3 " \
           "autonomous succeeded | 3 of 3 |" in lines
    assert f"{tmp_path / 'r_part'}: 2 runs" in "\n".join(lines)


def test_a_report_written_before_the_counts_were_kept_and_bad_files(tmp_path):
    exp = tmp_path / "exp"
    _experiment(exp)
    analyse([exp], tmp_path / "r")
    path = tmp_path / "r" / "convergence.csv"
    rows = list(csv.DictReader(open(path)))
    old = [k for k in rows[0] if not k.startswith(("eval_", "autonomous", "last_autonomous"))]
    with open(path, "w", newline="") as fh:  # the columns of the reports of issue 35's first 43 runs
        w = csv.DictWriter(fh, fieldnames=old, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    runs = {(r.method, r.seed): r for r in load_report_runs(tmp_path / "r")}
    assert runs[("khgrl", 0)].evaluation == ("episodes", 9, 10)  # from per_run.csv beside it
    assert runs[("khgrl", 0)].autonomous_counts() is None and runs[("khgrl", 0)].rows is None
    text = write_convergence([], tmp_path / "r2", list(runs.values()))
    assert "| KhGRL | 0 | 3 / 10 | episode 23 | ? |" in text
    assert "| HIL-SERL, its recipe | 0 | none in 10 / 320 spent | not reached in 10 | ? |" in text
    assert "| KhGRL | 14/20 = 70 % (95 % CI 48-85 %, Wilson) | episodes |" in text
    assert not (tmp_path / "r2" / "curves_fetch_moved.png").exists()  # no episodes, no curve
    with pytest.raises(FileNotFoundError, match="no convergence.csv"):
        load_report_runs(tmp_path)
    path.write_text(path.read_text().replace(",first,", ",third,", 1))
    with pytest.raises(ValueError, match="has milestones"):
        load_report_runs(tmp_path / "r")
    path.write_text("task,method\nfetch_moved,khgrl\n")
    with pytest.raises(ValueError, match="line 2: not a convergence.csv row"):
        load_report_runs(tmp_path / "r")
