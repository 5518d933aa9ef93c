"""What watching a run costs the robot (``khgrl bench view``): the passage world through ``khgrl up`` at a fixed rate,
the same seeded run without a view and with ``--view rerun:FILE.rrd`` (every step logged into a recording through
Rerun's gRPC sink), the two arms alternating ``repeats`` times so that machine noise hits both. Reported per run: the
actor's control-loop period p50 / p99 / max (its ``summary.json``), the steps, the wall time and the recording's size;
and the difference of the p99s (the target: within 2 ms). Before the runs, in this process: the cost of the logging
calls of one step (:meth:`~khgrl.common.rerun_log.RunLogger.step`, into a file) and of one Fetch camera image
(MuJoCo's offscreen render at 256 x 256 and its JPEG), what the actor pays per step and per image.

    khgrl bench view --episodes 6 --rate 50 --repeats 3 --out docs/view/bench_view.json
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["run_view_benchmark"]


def _up(run_dir: Path, episodes: int, rate: float, seed: int, rrd: Path | None) -> dict:
    argv = [sys.executable, "-m", "khgrl.deploy.cli", "up", "--scenario", "low_cov", "--method", "khgrl",
            "--episodes", str(episodes), "--seed", str(seed), "--rate", str(rate), "--run-dir", str(run_dir),
            "--overwrite", "--no-progress"]
    if rrd is not None:
        argv += ["--view", f"rerun:{rrd}"]
    t0 = time.monotonic()
    proc = subprocess.run(argv, capture_output=True, text=True, env={**os.environ, "RUST_LOG": "error"})
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"khgrl up failed ({proc.returncode}): {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    s = json.loads((run_dir / "actor-a0" / "summary.json").read_text())
    p = s["loop_period_ms"]
    return {"view": "rerun:FILE" if rrd is not None else "none", "p50_ms": round(p["p50"], 3),
            "p99_ms": round(p["p99"], 3), "max_ms": round(p["max"], 3), "steps": p["n"], "wall_s": round(wall, 1),
            "rrd_bytes": rrd.stat().st_size if rrd is not None and rrd.exists() else None,
            "episodes": _episodes(run_dir)}


def _episodes(run_dir: Path) -> list[str]:
    """episodes.csv's first 15 columns (those that do not depend on time): the same seeded run gives the same."""
    lines = (run_dir / "actor-a0" / "episodes.csv").read_text().splitlines()
    return [",".join(line.split(",")[:15]) for line in lines]


def _ms(samples: list[float]) -> dict:
    a = np.asarray(samples) * 1e3
    return {"p50_ms": round(float(np.median(a)), 3), "p99_ms": round(float(np.percentile(a, 99)), 3),
            "max_ms": round(float(a.max()), 3), "n": int(a.size)}


def _step_cost(steps: int = 1500) -> dict:
    """The logging calls of one step (a 2-D task), paced like a 100 Hz loop."""
    from khgrl.common.rerun_log import RunLogger, open_recording

    with tempfile.TemporaryDirectory() as tmp:
        rec = open_recording("bench", save=str(Path(tmp) / "bench.rrd"))
        log, proj, out = RunLogger(rec, "a0"), np.stack([np.eye(2)] * 300), []
        log.start(1, {"kmp_mean": np.zeros((300, 2)), "kmp_projector": proj, "via": np.zeros((0, 3))})
        for i in range(steps):
            t = i % 300
            iv = 100 < t < 180
            row = {"t": t, "robot": np.array([0.1 * t, 0.2]), "desired": np.array([0.1, 0.3]),
                   "mean": np.array([0.1, 0.25]), "scale": np.array([2.0, 3.0]),
                   "p_h": np.array([0.5, 0.5]) if iv else np.full(2, np.nan), "intervened": iv}
            t0 = time.perf_counter()
            log.step(1, row, proj[t])
            out.append(time.perf_counter() - t0)
            time.sleep(0.01)
        rec.flush()
        rec.disconnect()
    return _ms(out)


def _camera_cost(images: int = 40, size: int = 256) -> dict | None:
    """A Fetch camera image: MuJoCo's offscreen render and the JPEG the view logs (None: no offscreen OpenGL)."""
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import rerun as rr
        from khgrl.common.tasks.api import load_task
        from khgrl.common.tasks.kgrl_env import KGRLEnv

        env = KGRLEnv(load_task("fetch:moved"), seed=0)
        env.reset(seed=0)
        t0 = time.perf_counter()
        env.inner.camera_frame(size)
        first = time.perf_counter() - t0
        render, jpeg = [], []
        for _ in range(images):
            env.step(np.zeros(env.action_space.shape, np.float32))
            t0 = time.perf_counter()
            img = env.inner.camera_frame(size)
            render.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            rr.Image(img).compress(jpeg_quality=80)
            jpeg.append(time.perf_counter() - t0)
        env.close()
    except Exception as exc:  # noqa: BLE001 - no MuJoCo rendering here: the rest of the benchmark goes on
        print(f"no camera measurement: {exc!r}")
        return None
    return {"size": size, "first_ms": round(first * 1e3, 1), "render": _ms(render), "jpeg": _ms(jpeg)}


def _mean(rows: list[dict], view: str, key: str) -> float:
    vals = [r[key] for r in rows if r["view"] == view]
    return round(sum(vals) / len(vals), 3)


def run_view_benchmark(episodes: int = 6, rate: float = 50.0, repeats: int = 2, seed: int = 0,
                       work: str = "runs/bench-view", out: str | None = None) -> dict:
    """Runs both arms ``repeats`` times, alternating; prints a line per run and the summary, returns (and writes)
    the numbers.

    :param episodes: episodes per run.
    :param rate: the actor's control rate (Hz).
    :param repeats: pairs of runs.
    :param seed: the runs' seed (both arms: the same episodes).
    :param work: where the runs go.
    :param out: JSON file of the results.
    """
    if episodes < 1 or repeats < 1 or rate <= 0:
        raise ValueError("--episodes and --repeats must be >= 1 and --rate > 0")
    work_dir = Path(work).resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    step_cost, camera = _step_cost(), _camera_cost()
    print(f"logging calls of a step: p50 {step_cost['p50_ms']} ms, p99 {step_cost['p99_ms']} ms, max "
          f"{step_cost['max_ms']} ms", flush=True)
    if camera is not None:
        print(f"a Fetch camera image ({camera['size']} px): render p50 {camera['render']['p50_ms']} ms, p99 "
              f"{camera['render']['p99_ms']} ms (the first {camera['first_ms']} ms), JPEG p50 "
              f"{camera['jpeg']['p50_ms']} ms", flush=True)
    runs = []
    for i in range(repeats):
        for view in (False, True) if i % 2 == 0 else (True, False):
            rrd = work_dir / f"view-{i}.rrd" if view else None
            if rrd is not None:
                rrd.unlink(missing_ok=True)
            r = _up(work_dir / f"run-{i}-{'view' if view else 'none'}", episodes, rate, seed, rrd)
            runs.append(r)
            print(f"view {r['view']:10s}: loop period p50 {r['p50_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms, max "
                  f"{r['max_ms']:.1f} ms over {r['steps']} steps ({r['wall_s']:.0f} s)"
                  + (f", recording {r['rrd_bytes'] / 1e6:.2f} MB" if r["rrd_bytes"] else ""), flush=True)
    same = len({tuple(r.pop("episodes")) for r in runs}) == 1
    summary = {f"{k}_{v}": _mean(runs, v, k) for k in ("p50_ms", "p99_ms") for v in ("none", "rerun:FILE")}
    summary["p99_difference_ms"] = round(summary["p99_ms_rerun:FILE"] - summary["p99_ms_none"], 3)
    summary["within_2ms"] = summary["p99_difference_ms"] <= 2.0
    summary["same_episodes"] = same  # episodes.csv's columns 1-15 identical in every run, with the view or not
    print(f"mean over {repeats} pair(s): p50 {summary['p50_ms_none']} -> {summary['p50_ms_rerun:FILE']} ms, p99 "
          f"{summary['p99_ms_none']} -> {summary['p99_ms_rerun:FILE']} ms (difference {summary['p99_difference_ms']} "
          f"ms; target within 2 ms: {'yes' if summary['within_2ms'] else 'no'})")
    doc = {"machine": {"host": platform.node(), "cpus": os.cpu_count(), "load_average": os.getloadavg()},
           "settings": {"scenario": "low_cov", "method": "khgrl", "episodes": episodes, "rate_hz": rate,
                        "repeats": repeats, "seed": seed},
           "step_logging": step_cost, "camera_image": camera, "runs": runs, "summary": summary}
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {out}")
    return doc
