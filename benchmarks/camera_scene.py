"""How well the front camera finds ``panda:pick``'s cube: the estimate of :mod:`khgrl.common.tasks.panda.camera`
against the cube's true position over seeded scenes.

Scene k (k = 0..N-1) is ``panda:pick``'s environment (:class:`~khgrl.common.tasks.panda.arm.PandaPosition`, the
cube placed uniformly in gym-hil's sampling region) reset with seed k, the arm at gym-hil's home pose: the scene the
task's ``describe`` / ``via_points`` read. Each scene's front-camera frame is rendered with the cheap settings
(:func:`~khgrl.common.tasks.panda.camera.front_renderer`) and the cube located twice: with the occlusion model
(``locate_cube``'s default, what ``describe_from_camera`` uses) and without it (the centroid of the cube's pixels,
``occlusion=False``). Reported per method: the error |estimate - truth| in (x, y), millimetres (mean, median, p95,
max, and the mean signed error per axis), the scenes where the cube was not found (with the reason), and the time
per frame of rendering and estimating (median, mean); also the time of a few frames at gym-hil's own render settings
(shadow map 4096, 8 samples) for comparison.

    python -m khgrl.benchmarks.camera_scene --scenes 200 --out docs/camera_scene.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

__all__ = ["run_camera_scene_benchmark", "main"]

METHODS = {"occlusion": True, "centroid": False}  # locate_cube's occlusion flag


def _stats(errors: list[float]) -> dict[str, float | None]:
    """mean, median, p95, max of ``errors`` (None when empty)."""
    a = np.asarray(errors, np.float64)
    if not a.size:
        return {"mean": None, "median": None, "p95": None, "max": None}
    return {"mean": float(a.mean()), "median": float(np.median(a)), "p95": float(np.percentile(a, 95)),
            "max": float(a.max())}


def _ms(times: list[float]) -> dict[str, float]:
    """median and mean of ``times`` (s) in milliseconds."""
    return {"median_ms": float(np.median(times) * 1e3), "mean_ms": float(np.mean(times) * 1e3)}


def _default_render_s(model, data, frames: int, size: int) -> list[float]:
    """Seconds per frame of the front camera with gym-hil's own settings (a plain ``mujoco.Renderer``)."""
    import mujoco

    renderer = mujoco.Renderer(model, height=size, width=size)
    times = []
    try:
        for _ in range(frames):
            t0 = time.perf_counter()
            renderer.update_scene(data, camera="front")
            renderer.render()
            times.append(time.perf_counter() - t0)
    finally:
        renderer.close()
    return times


def _scene(env, seed: int, renderer, colours) -> tuple[dict, float]:
    """One scene's row (truth, each method's estimate or why not) and its render time (s)."""
    from khgrl.common.tasks.panda.camera import CubeNotFound, locate_cube, render_front

    env.reset(seed=seed)
    t0 = time.perf_counter()
    frame, cam = render_front(renderer, env.base.model, env.base.data)
    render_s = time.perf_counter() - t0
    truth = env.cube_pos
    row: dict = {"seed": seed, "true": [float(v) for v in truth]}
    for name, occlusion in METHODS.items():
        t0 = time.perf_counter()
        try:
            est = locate_cube(frame, cam, colours, occlusion=occlusion)
            row[name] = {"est": [float(v) for v in est], "error_mm": float(np.linalg.norm(est[:2] - truth[:2]) * 1e3),
                         "signed_mm": [float(v) for v in (est[:2] - truth[:2]) * 1e3]}
        except CubeNotFound as exc:
            row[name] = {"not_found": str(exc)}
        row[name]["estimate_s"] = time.perf_counter() - t0
    return row, render_s


def run_camera_scene_benchmark(scenes: int = 200, size: int = 128, default_frames: int = 3,
                               out: str | None = None) -> dict:
    """Locate the cube in ``scenes`` seeded scenes (see the module docstring); print and return the summary.

    :param scenes: N, scenes (reset seeds 0..N-1).
    :param size: frame width and height in pixels (gym-hil's image observations: 128).
    :param default_frames: frames timed with gym-hil's own render settings (0: none).
    :param out: also write the summary and the per-scene rows as JSON here.
    """
    import torch

    torch.set_num_threads(1)
    from khgrl.common.tasks.panda.arm import REGION, PandaPosition
    from khgrl.common.tasks.panda.camera import front_renderer
    from khgrl.common.tasks.panda.colours import scene_colours

    env = PandaPosition(region=REGION)
    renderer = None
    try:
        model = env.base.model
        colours = scene_colours(model)
        renderer = front_renderer(model, size)
        rows, renders = [], []
        for k in range(scenes):
            row, render_s = _scene(env, k, renderer, colours)
            rows.append(row)
            renders.append(render_s)
        default = _default_render_s(model, env.base.data, default_frames, size) if default_frames else []
    finally:
        if renderer is not None:
            renderer.close()
        env.close()
    summary: dict = {"scenes": scenes, "size": size, "render_cheap": _ms(renders),
                     "render_gym_hil_defaults": _ms(default) if default else None,
                     "colours": {"cube": vars(colours.cube), "table": vars(colours.table)}}
    for name in METHODS:
        found = [r[name] for r in rows if "est" in r[name]]
        summary[name] = {"found": len(found), "not_found": [(r["seed"], r[name]["not_found"]) for r in rows
                                                            if "not_found" in r[name]],
                         "error_mm": _stats([f["error_mm"] for f in found]),
                         "mean_signed_mm": (np.mean([f["signed_mm"] for f in found], 0).tolist() if found else None),
                         "estimate": _ms([r[name]["estimate_s"] for r in rows])}
    print(json.dumps(summary, indent=1))
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps({"summary": summary, "rows": rows}, indent=1) + "\n")
    return summary


def main(argv: list[str] | None = None) -> None:
    """``python -m khgrl.benchmarks.camera_scene``.

    :param argv: arguments (None: the command line's).
    """
    parser = argparse.ArgumentParser(prog="python -m khgrl.benchmarks.camera_scene",
                                     description="the cube's position from panda:pick's front camera vs the truth "
                                                 "over seeded scenes")
    parser.add_argument("--scenes", type=int, default=200, help="scenes, reset seeds 0..N-1 (default: %(default)s)")
    parser.add_argument("--size", type=int, default=128, help="frame width and height (default: %(default)s)")
    parser.add_argument("--default-frames", type=int, default=3,
                        help="frames timed with gym-hil's own render settings (default: %(default)s)")
    parser.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    args = parser.parse_args(argv)
    run_camera_scene_benchmark(scenes=args.scenes, size=args.size, default_frames=args.default_frames, out=args.out)


if __name__ == "__main__":
    main()
