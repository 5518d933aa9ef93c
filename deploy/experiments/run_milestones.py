"""What one run of a task reached, for ``khgrl report``'s convergence tables (deploy/experiments/convergence.py),
and the CSV form of it (``convergence.csv``), which an earlier report's runs can be read back from.

Per run, two milestones (episodes counted from 1; "autonomous" = no intervention step in the episode):

* ``first``: the first autonomous success;
* ``80/20``: the episode that completes the first window of 20 consecutive autonomous episodes (human-assisted ones
  skipped) with >= 80 % successes -- the criterion of ``--until-success 0.8``.

At each: the episode, the environment steps up to and including it, the **human steps** up to it (intervention
steps of those episodes plus the teacher's ``steps_driven``: the budget a person spends) and the wall seconds of
those episodes. A run that never reaches a milestone is censored: its values at the end of the run are lower bounds.

:func:`load_report_runs` reads the runs of an earlier report back from its ``convergence.csv``
(``khgrl report EXP --with-report DIR``): a run whose directory is on another machine, or gone, still enters the
tables beside the runs at hand. The CSV keeps each run's milestones, human budget, teacher steps, whether it
converged, its evaluation and its autonomous counts (reports written before those columns: the evaluation from
``per_run.csv`` beside it, the counts unknown); not its episodes, so such a run has no curve.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from khgrl.deploy.experiments.run_results import load_evaluation

__all__ = ["WINDOW", "RATE", "MILESTONES", "Milestone", "RunConvergence", "milestone_episode", "run_convergence",
           "csv_rows", "load_report_runs"]

WINDOW, RATE = 20, 0.8  # the 80/20 milestone
MILESTONES = ("first", "80/20")


@dataclass
class Milestone:
    """A run's values at a milestone; where not reached (``reached`` False) its values at the run's end."""

    reached: bool
    episodes: int
    steps: int
    human_steps: int
    wall_s: float


@dataclass
class RunConvergence:
    task: str
    method: str
    seed: int
    rows: list[dict] | None  # episode, steps, success, intervention_steps, wall_time (None: a run of an earlier
    # report, known by its convergence.csv alone: load_report_runs)
    teacher_steps: int  # the teacher's steps_driven (0 without a teacher)
    converged: bool  # ended early by --until-success
    milestones: dict[str, Milestone]
    human_budget: int  # the whole run's: intervention steps + teacher steps
    evaluation: tuple[str, int, int]  # (kind, successes, n) of load_evaluation
    counts: tuple[int, int, int, int] | None = None  # without rows: autonomous_counts as that report kept them
    source: str = ""  # without rows: the earlier report's directory

    def autonomous_counts(self) -> tuple[int, int, int, int] | None:
        """(autonomous episodes, their successes, the last ``WINDOW`` of them, their successes); None where not
        known (a run of an earlier report that did not keep them)."""
        if self.rows is None:
            return self.counts
        auto = [row["success"] for row in self.rows if row["intervention_steps"] == 0]
        last = auto[-WINDOW:]
        return len(auto), sum(auto), len(last), sum(last)


def milestone_episode(success: list[bool], human: list[bool], name: str) -> int | None:
    """Position (1-based, in the rows' order) of the episode that reaches a milestone, None if none does.

    :param success: each episode's success.
    :param human: whether each episode had an intervention step.
    :param name: ``first`` or ``80/20`` (:data:`MILESTONES`).
    """
    size, need = (1, 1) if name == "first" else (WINDOW, math.ceil(RATE * WINDOW - 1e-9))
    window: list[bool] = []
    for ep, (s, h) in enumerate(zip(success, human), start=1):
        if h:
            continue
        window = (window + [s])[-size:]
        if len(window) == size and sum(window) >= need:
            return ep
    return None


def _episodes(run_dir: Path) -> list[dict]:
    f = next(f for f in (run_dir / "actor-a0" / "episodes.csv", run_dir / "episodes.csv") if f.exists())
    with open(f, newline="") as fh:
        return [{"episode": int(r["episode"]), "steps": int(r.get("steps") or 0), "success": r["success"] == "True",
                 "intervention_steps": int(r["intervention_steps"]), "wall_time": float(r.get("wall_time") or 0.0)}
                for r in csv.DictReader(fh)]


def _json(path: Path) -> dict:
    try:
        return dict(json.loads(path.read_text()) or {})
    except (OSError, ValueError, TypeError):
        return {}


def run_convergence(task: str, method: str, seed: int, run_dir: Path) -> RunConvergence:
    """A run's milestones and human budget (module docstring).

    :param task: the task's label.
    :param method: the run's method (``khgrl``, ``hil-serl``, ...).
    :param seed: its seed.
    :param run_dir: the run directory (``actor-a0/episodes.csv``, ``actor-a0/summary.json``).
    """
    rows, summary = _episodes(Path(run_dir)), _json(Path(run_dir) / "actor-a0" / "summary.json")
    teacher = summary["teacher"] if "teacher" in summary else _json(Path(run_dir) / "actor-a0" / "teacher.json")
    teacher_steps = int((teacher or {}).get("steps_driven") or 0)  # teacher.json: a run without summary.json yet
    steps = np.cumsum([0] + [r["steps"] for r in rows], dtype=np.int64)
    human = teacher_steps + np.cumsum([0] + [r["intervention_steps"] for r in rows], dtype=np.int64)
    wall = np.cumsum([0.0] + [r["wall_time"] for r in rows])
    marks = {}
    for name in MILESTONES:
        at = milestone_episode([r["success"] for r in rows], [r["intervention_steps"] > 0 for r in rows], name)
        i = at if at is not None else len(rows)  # rows up to and including it (all of them: censored)
        marks[name] = Milestone(at is not None, rows[i - 1]["episode"] if i else 0, int(steps[i]), int(human[i]),
                                float(wall[i]))
    return RunConvergence(task, method, seed, rows, teacher_steps, summary.get("converged") is True, marks,
                          int(human[-1]), load_evaluation(Path(run_dir)))


COUNT_COLUMNS = ("autonomous", "autonomous_successes", "last_autonomous", "last_autonomous_successes")


def csv_rows(runs: list[RunConvergence]) -> list[dict]:
    out = []
    for r in runs:
        counts = dict(zip(COUNT_COLUMNS, r.autonomous_counts() or ("",) * len(COUNT_COLUMNS)))
        evaluation = dict(zip(("eval_kind", "eval_successes", "eval_episodes"), r.evaluation))
        out += [{"task": r.task, "method": r.method, "seed": r.seed, "milestone": name, "reached": m.reached,
                 "episodes": m.episodes, "steps": m.steps, "human_steps": m.human_steps, "wall_s": f"{m.wall_s:.3f}",
                 "teacher_steps": r.teacher_steps, "run_human_steps": r.human_budget, "converged": r.converged,
                 **evaluation, **counts} for name, m in r.milestones.items()]
    return out


def _evaluations(per_run: Path) -> dict[tuple[str, str, int], tuple[str, int, int]]:
    """{(task, method, seed): (kind, successes, n)} of a report's per_run.csv ({} where it has none)."""
    if not per_run.exists():
        return {}
    with open(per_run, newline="") as fh:
        return {(r["scenario"], r["method"], int(r["seed"])): (r.get("eval_kind") or "", int(r.get("eval_successes")
                or 0), int(r.get("eval_episodes") or 0)) for r in csv.DictReader(fh)}


def _run_from_csv(r: dict, source: str, evaluation: tuple[str, int, int]) -> RunConvergence:
    counts = tuple(int(r[c]) for c in COUNT_COLUMNS) if all(r.get(c) for c in COUNT_COLUMNS) else None
    if r.get("eval_kind") is not None:  # a report that kept the evaluation in convergence.csv
        evaluation = (r["eval_kind"], int(r.get("eval_successes") or 0), int(r.get("eval_episodes") or 0))
    return RunConvergence(r["task"], r["method"], int(r["seed"]), None, int(r["teacher_steps"]),
                          r["converged"] == "True", {}, int(r["run_human_steps"]), evaluation, counts, source)


def load_report_runs(report_dir: Path) -> list[RunConvergence]:
    """The runs of an earlier report, from its ``convergence.csv`` (module docstring); raises FileNotFoundError
    without one, ValueError for a file that is not one (a column or a milestone missing, a number that is none).

    :param report_dir: the earlier report's directory (``khgrl report EXP --out DIR``).
    """
    report_dir = Path(report_dir)
    path = report_dir / "convergence.csv"
    if not path.is_file():
        raise FileNotFoundError(f"{report_dir}: no convergence.csv (the directory of an earlier khgrl report)")
    evaluations = _evaluations(report_dir / "per_run.csv")
    runs: dict[tuple[str, str, int], RunConvergence] = {}
    with open(path, newline="") as fh:
        for line, r in enumerate(csv.DictReader(fh), start=2):
            try:
                key = (r["task"], r["method"], int(r["seed"]))
                run = runs.get(key) or _run_from_csv(r, str(report_dir), evaluations.get(key, ("", 0, 0)))
                run.milestones[r["milestone"]] = Milestone(r["reached"] == "True", int(r["episodes"]),
                                                           int(r["steps"]), int(r["human_steps"]), float(r["wall_s"]))
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{path}, line {line}: not a convergence.csv row ({exc!r})") from None
            runs[key] = run
    for (task, method, seed), run in runs.items():
        if set(run.milestones) != set(MILESTONES):
            raise ValueError(f"{path}: {task}-{method}-seed{seed} has milestones {sorted(run.milestones)}, "
                             f"expected {list(MILESTONES)}")
    return list(runs.values())
