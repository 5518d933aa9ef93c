"""The learner's gradient steps/s while a monitor floods its weights queryable (``khgrl bench queries``): a router,
a learner and one actor in robot mode (the learner trains as fast as it can on what it has), and, in alternating
windows, a separate process that sends ``get learner/weights`` at ``--qps`` queries a second (what any identity,
a ``monitor`` included, may do). Gradient steps/s come from the learner's own status (``gradient_steps`` over the
window). Reported: steps/s in the quiet and the flooded windows, their ratio, and the queries sent, answered and
the bytes the flooder received.

    khgrl bench queries --qps 1000 --seconds 15 --rounds 2
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["run_queries_benchmark"]

REPO = Path(__file__).resolve().parents[1]

FLOOD = """
import sys, time
from khgrl.common.delivery.transport import open_client
endpoint, key, qps, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
got = [0, 0]
def on_reply(r):
    if r.ok is not None:
        got[0] += 1
        got[1] += len(r.ok.payload)
with open_client(endpoint, timeout=20) as s:
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < seconds:
        s.get(key, on_reply, timeout=2.0)
        n += 1
        delay = t0 + n / qps - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    sent_s = time.monotonic() - t0
    time.sleep(2.5)
    print(n, round(sent_s, 3), got[0], got[1], flush=True)
"""


def _steps_per_s(samples: list[tuple[float, int]], t0: float, t1: float) -> float | None:
    """Gradient steps/s between the first and last status sample in [t0, t1]."""
    inside = [(t, g) for t, g in samples if t0 <= t <= t1]
    if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
        return None
    return (inside[-1][1] - inside[0][1]) / (inside[-1][0] - inside[0][0])


def run_queries_benchmark(qps: float = 1000.0, seconds: float = 15.0, rounds: int = 2, seed: int = 0,
                          work: str = "runs/bench-queries", out: str | None = None) -> dict:
    """Measure the learner's gradient steps/s with and without a weights-query flood (module docstring).

    :param qps: queries per second of the flood
    :param seconds: length of each quiet and each flooded window
    :param rounds: quiet/flooded window pairs
    :param seed: seed of the run
    :param work: run directory
    :param out: also write the results as JSON here
    """
    from khgrl.benchmarks.runtime.procs import BenchProcs, run_id
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys, ProtocolError, Status, decode

    work_dir = Path(work).resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    procs, run = BenchProcs(work_dir), run_id("queries")
    samples: list[tuple[float, int]] = []

    def on_status(sample) -> None:
        try:
            st = decode(Status, sample.payload.to_bytes())
        except ProtocolError:
            return
        samples.append((time.monotonic(), int(st.info.gradient_steps)))

    windows: list[dict] = []
    try:
        ep = procs.router()
        procs.learner("learner", run, ep, work_dir / run, "--learning-starts", "64", "--mode", "robot")
        procs.supervise(run, ep, work_dir / run)  # (robot mode: the actor moves only while supervised)
        actor = procs.actor("actor", run, ep, work_dir / run, "--episodes", "1000", "--rate", "50", "--mode",
                            "robot", "--seed", str(seed))
        keys = Keys(run)
        with open_client(ep, timeout=30) as session:
            sub = session.declare_subscriber(keys.status("learner", "learner"), on_status)
            deadline = time.monotonic() + 120
            while not samples or samples[-1][1] < 200:  # training has started
                if actor.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the learner did not start training: {actor.tail()}")
                time.sleep(0.5)
            for _ in range(rounds):
                t0 = time.monotonic()
                time.sleep(seconds)
                windows.append({"flood": False, "steps_per_s": _steps_per_s(samples, t0, time.monotonic())})
                t0 = time.monotonic()
                flood = subprocess.run([sys.executable, "-c", FLOOD, ep, keys.weights, str(qps), str(seconds)],
                                       cwd=REPO, text=True, capture_output=True, timeout=seconds + 120,
                                       env={**os.environ, "PYTHONPATH": str(REPO)})
                t1 = t0 + seconds + 1.0  # (the flooder's session takes about a second to open)
                n, sent_s, answered, nbytes = flood.stdout.split()
                windows.append({"flood": True, "steps_per_s": _steps_per_s(samples, t0 + 1.0, t1),
                                "queries": int(n), "queries_per_s": round(int(n) / float(sent_s), 1),
                                "answered": int(answered), "reply_mb": round(int(nbytes) / 1e6, 1)})
            sub.undeclare()
    finally:
        procs.close()
    quiet = [w["steps_per_s"] for w in windows if not w["flood"] and w["steps_per_s"]]
    flooded = [w["steps_per_s"] for w in windows if w["flood"] and w["steps_per_s"]]
    res = {"qps": qps, "seconds": seconds, "rounds": rounds, "windows": windows,
           "quiet_steps_per_s": round(sum(quiet) / len(quiet), 2) if quiet else None,
           "flood_steps_per_s": round(sum(flooded) / len(flooded), 2) if flooded else None, "cpus": os.cpu_count()}
    res["ratio"] = round(res["flood_steps_per_s"] / res["quiet_steps_per_s"], 3) if quiet and flooded else None
    for w in windows:
        extra = (f", {w['queries']} queries ({w['queries_per_s']}/s), {w['answered']} answered, "
                 f"{w['reply_mb']} MB of replies") if w["flood"] else ""
        sps = w["steps_per_s"]
        print(f"{'flood' if w['flood'] else 'quiet':>6}: {sps if sps is None else round(sps, 1)} gradient steps/s"
              f"{extra}")
    print(f"quiet {res['quiet_steps_per_s']} vs flooded {res['flood_steps_per_s']} gradient steps/s: ratio "
          f"{res['ratio']}")
    if out:
        Path(out).write_text(json.dumps(res, indent=2))
        print(f"wrote {out}")
    return res
