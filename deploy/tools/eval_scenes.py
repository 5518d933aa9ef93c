"""``khgrl eval --scenes K``: the policy on K seeded scenes (issue 22), and the per-scene CSV ``khgrl report`` reads.

Scene k (1-based) of an evaluation seeded S is reset with :func:`~khgrl.common.tasks.scene.scene_seed`
``(S, k, stream="eval")``: not the training episodes' stream, and the same scenes for every run evaluated with the
same seed (a paired comparison across methods). The placement of each scene is the task's
``Scene.describe`` of its first observation. On a task without a ``Scene`` every scene is the same one: the
output says so (:data:`FIXED_SCENE_NOTE`) and gives no interval, and the CSV has no placement columns.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
from khgrl.common.tasks.scene import MAX_PLACEMENT
from khgrl.deploy.tools.eval_inputs import EpisodeResult, EvalError
from khgrl.deploy.tools.intervals import rate_text

__all__ = ["FIXED_SCENE_NOTE", "SCENES_CSV", "scene_placement", "write_scenes_csv", "read_scenes_csv",
           "scene_lines", "scene_caption", "GIF_SCENES_MAX_FRAMES"]

FIXED_SCENE_NOTE = ("one scene (the task does not vary): this is one deterministic rollout repeated, not a success "
                    "rate over scenes")
SCENES_CSV = "scenes.csv"  # RUN_DIR/eval/scenes.csv: the default per-scene CSV (never overwritten: scenes-2.csv ...)
GIF_SCENES_MAX_FRAMES = 150  # the GIF's scenes together are subsampled to about this many frames
HEAD = ("scene", "seed", "varies")
RESULTS = ("success", "return", "env_return", "action_cost", "steps", "terminated")


def scene_placement(task: Any, env: Any) -> dict[str, float]:
    """The placement of the scene ``env`` was just reset to: ``task.scene.describe`` of its first observation
    ({} for a task without a scene), checked: at most 16 finite numbers, names not those of the CSV's own columns.

    :param task: the task.
    :param env: the :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`, right after ``reset``.
    :raises EvalError: a placement that is not that.
    """
    if task.scene is None:
        return {}
    try:  # (KGRLEnv reads it from the first observation at reset: env.placement)
        out = {str(k): float(v) for k, v in dict(env.placement).items()}
    except Exception as exc:  # noqa: BLE001 - the task's own function
        raise EvalError(f"task {task.name!r}: Scene.describe failed: {type(exc).__name__}: {exc}") from None
    bad = [k for k, v in out.items() if not math.isfinite(v)]
    clash = [k for k in out if k in HEAD or k in RESULTS]
    if len(out) > MAX_PLACEMENT or bad or clash:
        raise EvalError(f"task {task.name!r}: Scene.describe must give at most {MAX_PLACEMENT} finite numbers named "
                        f"other than {', '.join(HEAD + RESULTS)}; got {sorted(out)}")
    return out


def scene_caption(k: int, count: int, placement: dict[str, float]) -> str:
    """The line on a scene's GIF frames: ``scene 2/8  object_x=1.31 object_y=0.72``.

    :param k: the scene number.
    :param count: scenes in the evaluation.
    :param placement: the scene's placement.
    """
    return "  ".join([f"scene {k}/{count}", *(f"{n}={v:.3g}" for n, v in placement.items())])


def write_scenes_csv(path: Path, episodes: list[EpisodeResult], placements: list[dict[str, float]],
                     varies: bool) -> None:
    """The per-scene CSV: scene, seed, varies, the placement's columns (none on a fixed scene), success, return,
    env_return, action_cost, steps, terminated.

    :param path: the file (written as given: the caller picks a free name).
    :param episodes: the scenes' results (``episode`` is the scene number).
    :param placements: each scene's placement (the same names in every scene).
    :param varies: the task's scene varies (False: one fixed scene).
    :raises EvalError: scenes whose placements name different things.
    """
    names = list(placements[0]) if placements else []
    if any(list(p) != names for p in placements):
        raise EvalError(f"Scene.describe named different things in different scenes: {names} and "
                        f"{next(list(p) for p in placements if list(p) != names)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*HEAD, *names, *RESULTS])
        for e, p in zip(episodes, placements):
            w.writerow([e.episode, e.seed, varies, *(f"{p[k]:.10g}" for k in names), e.success, f"{e.ret:.10g}",
                        f"{e.env_return:.10g}", f"{e.action_cost:.10g}", e.steps, e.terminated])


def read_scenes_csv(path: Path) -> tuple[int, int, bool]:
    """(successes, scenes, varies) of a per-scene CSV.

    :param path: the file (``khgrl eval --scenes``).
    :raises ValueError: not such a file.
    """
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or "success" not in rows[0] or "varies" not in rows[0]:
        raise ValueError(f"{path}: not a khgrl eval --scenes CSV (no rows, or no success / varies column)")
    return sum(r["success"] == "True" for r in rows), len(rows), rows[0]["varies"] == "True"


def _summary(episodes: list[EpisodeResult]) -> str:
    r = np.array([e.ret for e in episodes], dtype=np.float64)
    return f"return {r.mean():.2f} ± {r.std():.2f}; steps {np.mean([e.steps for e in episodes]):.1f}"


def scene_lines(episodes: list[EpisodeResult], placements: list[dict[str, float]], varies: bool, seed: int,
                region: str) -> list[str]:
    """What ``khgrl eval --scenes`` prints: the scenes' seeds and region, one line per scene (its placement), the
    success rate with its Wilson interval, or on a fixed scene the rate and :data:`FIXED_SCENE_NOTE`.

    :param episodes: the scenes' results.
    :param placements: their placements.
    :param varies: the task's scene varies.
    :param seed: the evaluation's seed S (scene k: scene_seed(S, k, "eval")).
    :param region: the task's ``Scene.region`` ("" for a fixed scene).
    """
    where = f"region: {region}" if varies else "one scene (the task does not vary)"
    lines = [f"{len(episodes)} scenes, scene k reset with scene_seed({seed}, k, stream='eval'); {where}",
             f"{'scene':>5} {'seed':>10} {'steps':>6} {'return':>10} {'env':>10} {'r_a':>9}  success"
             + ("  placement" if varies else "")]
    for e, p in zip(episodes, placements):
        where = "  " + " ".join(f"{k}={v:.3g}" for k, v in p.items()) if p else ""
        lines.append(f"{e.episode:>5} {e.seed:>10} {e.steps:>6} {e.ret:>10.2f} {e.env_return:>10.2f} "
                     f"{e.action_cost:>9.2f}  {'yes' if e.success else 'no ':<7}{where}".rstrip())
    n_ok = sum(e.success for e in episodes)
    if varies:
        lines.append(f"success {rate_text(n_ok, len(episodes))}; {_summary(episodes)}")
    else:
        lines += [f"success {n_ok}/{len(episodes)} ({100 * n_ok / len(episodes):.0f} %); {_summary(episodes)}",
                  FIXED_SCENE_NOTE]
    return lines
