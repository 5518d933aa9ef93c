"""Is ``fetch:random`` / ``fetch:obstacle`` solvable, and does ``fetch:obstacle`` need the human? Scripted rollouts
over K seeded scenes (``scene_seed(seed, k)``, k = 1..K), no learning, no policy:

* **teacher**: the mean of the scripted teacher's demonstrations re-targeted to the observed object (the mean
  "adapted by hand");
* **unadapted**: the LC-NS-KMP mean of the demonstrations (at ``DEMO_OBJECT``), as ``--no-adapt`` runs it;
* **adapted**: the LC-NS-KMP mean adapted by the task's via-points (the rule of ``common/kmp/adapt.py``: each
  via-point replaces the reference point at its grid step; computed here directly);

each without and with the task's scripted human (its P_h in place of the mean where it gives one). Prints the
success count, the scenes in which anything touched the obstacle, the largest |adapted mean - via-point| and the
median time per environment step and reset.

    python -m khgrl.benchmarks.fetch_scenes --scenes 20 --seed 3
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from khgrl.common.kmp.fit import box_constraints
from khgrl.common.kmp.gmr import reference_distribution
from khgrl.common.kmp.kernels import RBF
from khgrl.common.kmp.lcnskmp import LCNSKMP
from khgrl.common.tasks.api import Task, load_task, scene_seed
from khgrl.common.tasks.fetch.teacher import teacher_demos

__all__ = ["adapted_mean", "rollout", "measure", "main"]

MODES = ("unadapted", "unadapted+human", "teacher", "teacher+human", "adapted", "adapted+human")


def adapted_mean(task: Task, vias) -> np.ndarray:
    """(N, O) the task's LC-NS-KMP mean with each via-point in place of the reference point at its grid step.

    :param task: the task (its demonstrations, KMP settings and workspace).
    :param vias: the via-points.
    """
    cfg, n = task.kmp, task.demos.shape[1]
    ref = reference_distribution(task.demos, n_components=cfg.n_components, seed=cfg.seed, jitter=cfg.jitter)
    mu, sigma = ref.mu.copy(), ref.sigma.copy()
    for v in vias:
        t = int(round(v.phase * (n - 1)))
        mu[t], sigma[t] = v.position, np.eye(mu.shape[1]) / v.precision
    G, c = box_constraints(np.asarray(task.workspace[0]), np.asarray(task.workspace[1]))
    model = LCNSKMP(ref.s, mu, sigma, lam=cfg.lam, beta=cfg.beta, kernel=RBF(length_scale=cfg.length_scale),
                    constraints=(G, c))
    return np.asarray(model.grid_mean)


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
    env = task.make_env(seed)
    out = {m: [] for m in MODES}
    resets, steps, via_err = [], [], []
    for k in range(1, scenes + 1):
        for mode in MODES:
            t0 = time.perf_counter()
            obs, _ = env.reset(seed=scene_seed(seed, k))
            resets.append(time.perf_counter() - t0)
            if mode.startswith("unadapted"):
                path = adapted_mean(task, [])
            elif mode.startswith("teacher"):
                path = teacher_demos(n=task.demos.shape[1], obj=obs[3:6].copy()).mean(axis=0)
            else:
                vias = list(task.scene.via_points(obs))
                path = adapted_mean(task, vias)
                n = len(path)
                via_err.append(max(float(np.linalg.norm(path[int(round(v.phase * (n - 1)))] - v.position))
                                   for v in vias))
            ok, touching, per_step = rollout(env, obs, path, task.scripted_human if "human" in mode else None)
            out[mode].append((ok, touching))
            steps.append(per_step)
    env.close()
    return {"modes": out, "reset_s": float(np.median(resets)), "step_s": float(np.median(steps)),
            "via_err_m": max(via_err)}


def main(argv: list[str] | None = None) -> int:
    """Print the measurements (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--tasks", nargs="+", default=["fetch:random", "fetch:obstacle"])
    args = ap.parse_args(argv)
    for spec in args.tasks:
        r = measure(spec, args.scenes, args.seed)
        print(f"{spec}: {args.scenes} scenes (seed {args.seed}); median reset {r['reset_s'] * 1e3:.1f} ms, step "
              f"{r['step_s'] * 1e3:.2f} ms; adapted mean within {r['via_err_m'] * 1e3:.2f} mm of every via-point")
        for mode, res in r["modes"].items():
            print(f"  {mode:15s} success {sum(ok for ok, _ in res):2d}/{len(res)}; scenes touching the obstacle "
                  f"{sum(t > 0 for _, t in res):2d}/{len(res)}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
