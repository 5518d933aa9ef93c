"""Frames from many actors into one learner (``khgrl bench images``, issue 37 point 7): the real ``khgrl up`` with N
actors in robot mode at a fixed rate, each observing two 128 x 128 RGB cameras
(``khgrl.deploy.examples.camera_task:make_two_cameras``: the passage world drawn into both images), against the same
world observed as a state vector only (``passage:high_cov``), one case after the other, each ``seconds`` from its
first ingested batch, then Ctrl-C (:func:`~khgrl.benchmarks.scale.scale_case` measures it):

* **ingest**: transitions per second the learner stored, and **exactly once** after Ctrl-C (lost, duplicated);
* **actor loop p99** (each actor's loop period, the worst actor), camera against state-only (the issue's target:
  within 2 ms);
* **CPU per transition** by role (router, learner, actors): the cores each kept busy over the case, over its
  ingest rate -- what shared memory saves, if anything, is the copies through the router's sockets;
* **learner RSS** (peak), and the **resident bytes per transition** it took: the growth of its RSS from its first
  status to its last over the transitions it ingested in between (frames stored once: one frame per transition
  and camera, plus one per episode);
* what a transition costs on the wire is what the frames weigh: 2 x 49,152 bytes.

The data path alone: no training (``--learning-starts`` past the run's end, so the actors act uniformly at random
and the learner only ingests, journals and checkpoints; a gradient step from two 128 x 128 cameras costs seconds on
a CPU, benchmarks/pixels_step.py). The camera case runs twice: frames as copies through the Zenoh router (KhGRL's
default), and on Zenoh's shared memory (``--zenoh-config deploy/zenoh/shared-memory.json5``: a put of more than 3 KB
is written once into its publisher's pool in /dev/shm and handed on by reference).

    khgrl bench images --actors 8 --rate 20 --seconds 60 --out docs/bench_images.json
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

from khgrl.benchmarks.scale import scale_case

__all__ = ["run_images_benchmark", "CASES"]

# no training; a replay of 12,000 transitions (a case's 60 s of 8 actors at 20 Hz is 9,600: none overwritten, the
# frame store sized to what the case holds); the supervisor's heartbeat given 5 s
# (0.4 by default) on a machine these actors load fully: a late heartbeat latches the e-stop
BENCH_FLAGS = ("--learning-starts", str(10**9), "--buffer-size", "12000", "--supervision-timeout", "5")
CAMERAS = ("--task", "khgrl.deploy.examples.camera_task:make_two_cameras")
SHARED_MEMORY = Path(__file__).resolve().parents[1] / "deploy" / "zenoh" / "shared-memory.json5"
CASES = {  # name: khgrl up flags
    "state": ("--task", "passage:high_cov"),
    "2 cameras 128x128": CAMERAS,
    "2 cameras, shared memory": (*CAMERAS, "--zenoh-config", str(SHARED_MEMORY)),
}


def _bytes_per_transition(case: dict) -> float:
    """The learner's RSS growth over the case per transition ingested (NaN without two statuses)."""
    rss, n = case["rss_mb_series"], case["produced"]
    return (rss[-1] - rss[0]) * 2**20 / n if len(rss) >= 2 and n > 0 else float("nan")


def run_images_benchmark(actors: int = 8, rate: float = 20.0, seconds: float = 60.0, seed: int = 0,
                         work: str = "runs/bench-images", out: str | None = None) -> list[dict]:
    """Run the state-only case and the camera cases; print a line each and the differences (and write JSON to
    ``out``).

    :param actors: actors of each case
    :param rate: their control rate in Hz
    :param seconds: how long each case runs from its first ingested batch
    :param seed: seed of the runs
    :param work: where the run directories go
    :param out: JSON file of the results
    """
    if actors < 1 or rate <= 0 or seconds <= 0:
        raise ValueError(f"--actors {actors}, --rate {rate}, --seconds {seconds}: each must be > 0")
    work_dir = Path(work).resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for name, flags in CASES.items():
        r = {"case": name, **scale_case(work_dir, actors, rate, "robot", seconds, seed, extra=(*flags, *BENCH_FLAGS))}
        r["resident_bytes_per_transition"] = round(_bytes_per_transition(r))
        r["cpu_ms_per_transition"] = {k: round(1e3 * v / r["ingest_per_s"], 2) if r["ingest_per_s"] > 0 else None
                                      for k, v in r["cores_busy"].items()}
        results.append(r)
        print(f"{name:>24}: {actors} actors at {rate:g} Hz, startup {r['startup_s']:.1f} s, ingest "
              f"{r['ingest_per_s']:.1f}/s, loop p99 {r['actor_loop_ms_p99']:.2f} ms, learner RSS peak "
              f"{r['rss_mb_peak']:.0f} MB, {r['resident_bytes_per_transition']:,} resident bytes/transition, "
              f"produced {r['produced']}, lost {r['lost']}, duplicated {r['duplicated']}; CPU ms per transition "
              f"{r['cpu_ms_per_transition']}", flush=True)
    state = results[0]
    for cams in results[1:]:
        print(f"{cams['case']} - state: loop p99 {cams['actor_loop_ms_p99'] - state['actor_loop_ms_p99']:+.2f} ms, "
              f"ingest {cams['ingest_per_s'] / max(state['ingest_per_s'], 1e-9):.2f}x", flush=True)
    if out:
        doc = {"machine": {"host": platform.node(), "cpus": os.cpu_count()}, "actors": actors, "rate_hz": rate,
               "seconds": seconds, "seed": seed, "cases": results}
        Path(out).write_text(json.dumps(doc, indent=2))
        print(f"wrote {out}")
    return results
