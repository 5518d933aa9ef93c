"""Is ``fetch:random`` / ``fetch:obstacle`` solvable, and does ``fetch:obstacle`` need the human? Scripted rollouts
over K seeded scenes (``scene_seed(seed, k)``, k = 1..K), no learning, no policy:

* **teacher**: the mean of the scripted teacher's demonstrations re-targeted to the observed object (the mean
  "adapted by hand");
* **unadapted**: the LC-NS-KMP mean of the demonstrations (at ``DEMO_OBJECT``), as ``--no-adapt`` runs it;
* **adapted**: the LC-NS-KMP mean adapted by the task's via-points (``common/kmp/adapt.py``, what the actor drives
  with);

each without and with the task's scripted human (its P_h in place of the mean where it gives one). Prints the
success count, the scenes in which anything touched the obstacle, the largest |adapted mean - via-point| and the
median time per environment step and reset.

    khgrl bench fetch-scenes --scenes 20 --seed 3
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from khgrl.common.kmp.adapt import adapt_model
from khgrl.common.tasks.api import load_task, scene_seed
from khgrl.common.tasks.fetch.teacher import teacher_demos
from khgrl.common.tasks.world import build_task_world

__all__ = ["adapted_mean", "rollout", "measure", "run_fetch_scenes_benchmark"]

MODES = ("unadapted", "unadapted+human", "teacher", "teacher+human", "adapted", "adapted+human")


def adapted_mean(world, vias) -> np.ndarray:
    """(N, O) the task's LC-NS-KMP mean adapted to ``vias`` (:func:`~khgrl.common.kmp.adapt.adapt_model`, what the
    actor drives with; no via-points: the demonstrations' mean).

    :param world: the task's built world (its LC-NS-KMP under the workspace box).
    :param vias: the via-points.
    """
    return np.asarray(adapt_model(world.model, vias).grid_mean)


def rollout(env, obs: np.ndarray, path: np.ndarray, human=None) -> tuple[bool, int, float]:
    """Command ``path`` (the human's P_h where it gives one): (success, steps touching the obstacle, s per step).

    :param env: the task's environment, just reset.
    :param obs: its first observation.
    :param path: (N, 3) desired positions.
    :param human: the task's scripted human (None: none).
    """
    n, touching, info = len(path), 0, {}
    t0 = time.perf_counter()
    for t in range(n):
        p_h = None if human is None else human(path[t], phase=t / (n - 1), position=obs[:3], obs=obs)
        obs, _, _, _, info = env.step(path[t] if p_h is None else p_h)
        touching += info.get("obstacle_contacts", 0) > 0
    return bool(info["success"]), touching, (time.perf_counter() - t0) / n


def measure(spec: str, scenes: int, seed: int) -> dict:
    """Results of every mode over ``scenes`` scenes of task ``spec``.

    :param spec: e.g. "fetch:random".
    :param scenes: K.
    :param seed: the run seed of the scenes.
    """
    task = load_task(spec)
    world = build_task_world(task)
    env = task.make_env(seed)
    out = {m: [] for m in MODES}
    resets, steps, via_err = [], [], []
    for k in range(1, scenes + 1):
        for mode in MODES:
            t0 = time.perf_counter()
            obs, _ = env.reset(seed=scene_seed(seed, k))
            resets.append(time.perf_counter() - t0)
            if mode.startswith("unadapted"):
                path = adapted_mean(world, [])
            elif mode.startswith("teacher"):
                path = teacher_demos(n=task.demos.shape[1], obj=obs[3:6].copy()).mean(axis=0)
            else:
                vias = list(task.scene.via_points(obs))
                path = adapted_mean(world, vias)
                n = len(path)
                via_err.append(max(float(np.linalg.norm(path[int(round(v.phase * (n - 1)))] - v.position))
                                   for v in vias))
            ok, touching, per_step = rollout(env, obs, path, task.scripted_human if "human" in mode else None)
            out[mode].append((ok, touching))
            steps.append(per_step)
    env.close()
    return {"modes": out, "reset_s": float(np.median(resets)), "step_s": float(np.median(steps)),
            "via_err_m": max(via_err)}


def run_fetch_scenes_benchmark(scenes: int = 20, seed: int = 3, tasks: tuple[str, ...] = ("fetch:random",
                               "fetch:obstacle"), out: str | None = None) -> dict:
    """Print the measurements (see the module docstring) and return them.

    :param scenes: K scenes per task.
    :param seed: the run seed of the scenes.
    :param tasks: task specs.
    :param out: also write them as JSON here.
    """
    record = {}
    for spec in tasks:
        r = measure(spec, scenes, seed)
        record[spec] = {**r, "modes": {m: {"success": sum(ok for ok, _ in res), "touching": sum(t > 0 for _, t in res),
                                           "scenes": len(res)} for m, res in r["modes"].items()}}
        print(f"{spec}: {scenes} scenes (seed {seed}); median reset {r['reset_s'] * 1e3:.1f} ms, step "
              f"{r['step_s'] * 1e3:.2f} ms; adapted mean within {r['via_err_m'] * 1e3:.2f} mm of every via-point")
        for mode, res in record[spec]["modes"].items():
            print(f"  {mode:15s} success {res['success']:2d}/{res['scenes']}; scenes touching the obstacle "
                  f"{res['touching']:2d}/{res['scenes']}")
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(record, indent=2))
    return record
