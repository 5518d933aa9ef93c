"""The runs of an experiment and their learning criteria (``khgrl experiment`` output, read by ``khgrl report``).

An experiment directory holds one run directory per (scenario, method, seed), named
``<scenario>-<method>-seed<S>`` (``khgrl up`` runs: ``actor-a0/episodes.csv``; ``khgrl reference`` runs:
``episodes.csv``). This module finds them, reads their episode rows, scale tables and corrections, and computes
each run's learning criteria (all in episodes, counted from 1; ``None`` = never within the run):

* first success; first success without human help (no intervention in that episode)
* **stable success**: the first episode of the first 5 consecutive *autonomous* episodes (no human
  intervention) that all succeed -- human-assisted episodes are skipped, neither counted nor breaking the run
* **zero obstacle cost**: the episode from which no later episode touches the obstacle (obstacle cost 0
  in that episode and every one after it)
* success rate over the last 10 episodes; episodes with a collision (obstacle cost < 0) during learning
* the success rate of the final policy in ``khgrl eval RUN`` where it was run: over seeded scenes
  (``khgrl eval --scenes``: ``RUN/eval/scenes.csv``, with its Wilson interval), else over episodes
  (``RUN/eval/eval.csv``); on a task whose scene does not vary it is "one scene", one deterministic rollout repeated,
  not a success rate (:func:`load_evaluation`)
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "RUN_NAME",
    "STABLE_WINDOW",
    "METHOD_LABEL",
    "RunResult",
    "stable_success",
    "zero_cost_from",
    "find_runs",
    "load_run",
    "summarize_run",
    "episode_matrix",
    "human_episodes",
    "load_scale",
    "load_eval",
    "load_evaluation",
    "EVAL_KINDS",
    "corrected_phases",
]

# <scenario>: a passage-world scenario (high_cov, low_cov) or a task's label (fetch_moved: ``khgrl experiment --tasks``)
# <method>: khgrl, kgrl, or either with "_noadapt" (khgrl up --no-adapt: the demonstrations' KMP in every scene) or
# "_rlpd" (--sampling rlpd); hil-serl, hil-serl_episode (--takeover episode) or hil-serl_recipe (--recipe hil-serl)
RUN_NAME = re.compile(r"^(?P<scenario>[A-Za-z0-9_]+)-"
                      r"(?P<method>(?:khgrl|kgrl)(?:_noadapt|_rlpd)?|hil-serl(?:_episode|_recipe)?)-seed(?P<seed>\d+)$")
STABLE_WINDOW = 5  # consecutive autonomous successes that count as "stable success"
METHOD_LABEL = {"khgrl": "KhGRL", "kgrl": "KGRL", "khgrl_noadapt": "KhGRL, no adaptation",
                "kgrl_noadapt": "KGRL, no adaptation", "khgrl_rlpd": "KhGRL + RLPD replay",
                "kgrl_rlpd": "KGRL + RLPD replay", "hil-serl": "HIL-SERL",
                "hil-serl_episode": "HIL-SERL, whole-episode takeover", "hil-serl_recipe": "HIL-SERL, its recipe"}


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
    eval_success: float | None = None  # success rate of ``khgrl eval RUN`` (RUN/eval/eval.csv), if it was run
    eval_episodes: int = 0  # episodes or scenes evaluated
    eval_successes: int = 0
    eval_kind: str = ""  # one of EVAL_KINDS
    violation_steps: int = 0  # commanded positions that violated a hard constraint, whole run
    workspace_exits: int = 0  # policy commands outside the workspace box, whole run
    human_steps_to_first_autonomous: int | None = None  # human steps in the episodes up to it (None: never)
    gradient_steps: int | None = None  # the learner's, at its last checkpoint (None: not recorded)
    wall_s: float | None = None  # the run's wall time (khgrl up's summary.json)
    demo_steps: int | None = None  # prior transitions from demonstrations (the teacher's or the task's replayed)


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
             "clipped_steps": int(r["clipped_steps"]), "violation_steps": int(r.get("violation_steps") or 0),
             "workspace_exits": int(r.get("workspace_exits") or 0)} for r in rows]


def run_compute(run_dir: Path) -> tuple[int | None, float | None]:
    """(the learner's gradient steps at its last checkpoint, the run's wall seconds); None where not recorded."""
    def read(path: Path) -> dict:
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}

    steps = read(Path(run_dir) / "learner" / "checkpoint" / "state.json").get("gradient_steps")
    wall = read(Path(run_dir) / "summary.json").get("wall_time_s")
    return (int(steps) if isinstance(steps, int) else None), (float(wall) if isinstance(wall, (int, float)) else None)


def demo_steps(run_dir: Path) -> int | None:
    """The demonstrations' steps the run's first actor sent as prior data (``demo_transitions`` of
    actor-a0/summary.json: the teacher's successful ones, or the task's replayed); None where not recorded."""
    try:
        value = json.loads((Path(run_dir) / "actor-a0" / "summary.json").read_text()).get("demo_transitions")
    except (OSError, ValueError, AttributeError):
        return None
    return int(value) if isinstance(value, int) else None


def load_eval(run_dir: Path) -> list[bool]:
    """Success of each episode of the run's first ``khgrl eval`` (RUN/eval/eval.csv; [] if it was not run)."""
    f = Path(run_dir) / "eval" / "eval.csv"
    if not f.exists():
        return []
    with open(f, newline="") as fh:
        return [r["success"] == "True" for r in csv.DictReader(fh)]


EVAL_KINDS = ("", "episodes", "scenes", "one scene")  # none; eval.csv; scenes.csv of a varying task; a fixed scene


def load_evaluation(run_dir: Path) -> tuple[str, int, int]:
    """(kind, successes, episodes) of the run's evaluation (:data:`EVAL_KINDS`; ("", 0, 0) if it was not evaluated):
    its first ``khgrl eval --scenes`` (RUN/eval/scenes.csv) if there is one, else its first ``khgrl eval``
    (RUN/eval/eval.csv). "one scene": the task's scene does not vary (the scenes CSV says so; for eval.csv the
    run's task is loaded from its config.json: a task without a Scene).

    :param run_dir: the run directory.
    """
    from khgrl.deploy.tools.eval_scenes import SCENES_CSV, read_scenes_csv

    scenes = Path(run_dir) / "eval" / SCENES_CSV
    if scenes.exists():
        k, n, varies = read_scenes_csv(scenes)
        return ("scenes" if varies else "one scene"), k, n
    evaluated = load_eval(run_dir)
    if not evaluated:
        return "", 0, 0
    kind = "one scene" if _task_varies(Path(run_dir)) is False else "episodes"
    return kind, sum(evaluated), len(evaluated)


_VARIES: dict[str, bool | None] = {}


def _task_varies(run_dir: Path) -> bool | None:
    """Whether the run's task (its config.json) has a varying scene; None where that cannot be told."""
    from khgrl.common.config.settings import read_run_file
    from khgrl.common.tasks.api import load_task

    try:
        cfg, _ = read_run_file(run_dir / "config.json")
        spec = cfg.task_spec
    except (OSError, ValueError):
        return None
    if spec not in _VARIES:
        try:
            _VARIES[spec] = load_task(spec).scene is not None
        except Exception:  # noqa: BLE001 - a task module that is not importable here: not known
            _VARIES[spec] = None
    return _VARIES[spec]


def summarize_run(scenario: str, method: str, seed: int, run_dir: Path, rows: list[dict]) -> RunResult:
    succ = [r["success"] for r in rows]
    kind, eval_ok, eval_n = load_evaluation(run_dir)
    human = [r["intervention_steps"] > 0 for r in rows]
    last = rows[-10:]
    first_auto = next((r["episode"] for r, h in zip(rows, human) if r["success"] and not h), None)
    steps, wall = run_compute(run_dir)
    return RunResult(
        scenario=scenario, method=method, seed=seed, path=str(run_dir), episodes=len(rows), successes=sum(succ),
        success_last_10=sum(r["success"] for r in last) / max(1, len(last)),
        first_success=next((r["episode"] for r in rows if r["success"]), None),
        first_success_without_human=first_auto,
        stable_success=stable_success(succ, human),
        zero_obstacle_cost_from=zero_cost_from([r["obstacle_cost"] for r in rows]),
        collision_episodes=sum(r["obstacle_cost"] < 0 for r in rows),
        obstacle_steps=sum(r["obstacle_steps"] for r in rows),
        human_episodes=sum(human), intervention_steps=sum(r["intervention_steps"] for r in rows),
        clipped_human_steps=sum(r["clipped_steps"] for r in rows),
        mean_return_last_10=float(np.mean([r["ret"] for r in last])) if last else float("nan"),
        eval_success=eval_ok / eval_n if eval_n else None, eval_episodes=eval_n, eval_successes=eval_ok,
        eval_kind=kind, violation_steps=sum(r["violation_steps"] for r in rows),
        workspace_exits=sum(r["workspace_exits"] for r in rows),
        human_steps_to_first_autonomous=None if first_auto is None else sum(
            r["intervention_steps"] for r in rows if r["episode"] < first_auto),
        gradient_steps=steps, wall_s=wall, demo_steps=demo_steps(run_dir),
    )


def episode_matrix(runs: list[list[dict]], key: str, episodes: int) -> np.ndarray:
    """(seeds, episodes) of one per-episode quantity; NaN where a run is shorter."""
    m = np.full((len(runs), episodes), np.nan)
    for i, rows in enumerate(runs):
        for r in rows[:episodes]:
            m[i, r["episode"] - 1] = float(r[key])
    return m


def human_episodes(runs: list[list[dict]]) -> list[int]:
    """Episodes (1-based) in which any of the runs had a human intervention."""
    eps = set()
    for rows in runs:
        eps |= {r["episode"] for r in rows if r["intervention_steps"] > 0}
    return sorted(eps)


def load_scale(run_dir: Path, scenario: str) -> tuple[np.ndarray, np.ndarray, bool]:
    """(phases (N,), L (N, O), recorded) at the end of a run. Runs without a recorded table (single-process
    reference KGRL, or runs made before the actor wrote ``scale.npz``) never refit L: the scenario's default
    (passage-world scenarios only; a task's run without ``scale.npz`` is an error)."""
    from khgrl.common.tasks.passage.scenarios import SCENARIOS, get_scenario

    f = run_dir / "actor-a0" / "scale.npz"
    if f.exists():
        d = np.load(f)
        return d["phases"], d["table"], True
    if (run_dir / "scale_table.npy").exists():
        table = np.load(run_dir / "scale_table.npy")
        return np.linspace(0.0, 1.0, table.shape[0]), table, True
    if scenario not in SCENARIOS:
        raise FileNotFoundError(f"{run_dir}: no actor-a0/scale.npz (the exploration scale at the end of the run)")
    sc = get_scenario(scenario)
    n = 400
    return np.linspace(0.0, 1.0, n), np.full((n, 2), sc.default_scale), False


def corrected_phases(run_dir: Path, n: int) -> np.ndarray:
    """Phases (step / (n - 1)) of the corrections the human made in a run (none without corrections.csv)."""
    f = run_dir / "actor-a0" / "corrections.csv"
    if not f.exists():
        return np.zeros(0)
    with open(f, newline="") as fh:
        steps = [int(r["step"]) for r in csv.DictReader(fh)]
    return np.asarray(steps, dtype=np.float64) / (n - 1)
