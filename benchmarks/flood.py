"""The actor's 50 Hz control loop during a flood (``khgrl bench flood``): a router, a learner and one actor at
``--rate`` Hz (robot mode: it never waits for the learner); after a quiet warm-up, a separate process publishes
N small garbage messages as fast as it can on the actor's correction and control keys (what any process on an
open router can do). The loop's step times come from the actor's own frames (one per step; the envelope's
timestamp is taken when the step is published), so the periods are the loop's, measured outside the actor.
Reported: loop period p50/p99/max before, during and after the flood, against the target ``1/rate``; the flood's
duration and how many messages the actor rejected (its summary).

    khgrl bench flood --messages 100000 --rate 50
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["run_flood_benchmark"]

REPO = Path(__file__).resolve().parents[1]

FLOOD = """
import os, sys, time
from khgrl.common.delivery.transport import open_client
endpoint, run, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
with open_client(endpoint, timeout=20) as s:
    pubs = [s.declare_publisher(f"khgrl/{run}/human/flood/correction"), s.declare_publisher(f"khgrl/{run}/control/all")]
    time.sleep(0.5)
    t0 = time.time()
    for i in range(n):
        pubs[i % 2].put(os.urandom(1 + i % 64))
    print(t0, time.time(), flush=True)
    time.sleep(1.0)
"""


def _periods(steps: list[tuple[int, int, float]], t0: float, t1: float) -> np.ndarray:
    """Periods (ms) between consecutive steps of one episode whose later step was taken in [t0, t1)."""
    out = []
    for (e0, s0, a), (e1, s1, b) in zip(steps, steps[1:]):
        if e0 == e1 and s1 == s0 + 1 and t0 <= b < t1:
            out.append((b - a) * 1e3)
    return np.asarray(out)


def _stats(p: np.ndarray) -> dict:
    if not p.size:
        return {"n": 0}
    q = lambda x: round(float(np.percentile(p, x)), 2)  # noqa: E731
    return {"n": int(p.size), "p50": q(50), "p99": q(99), "max": round(float(p.max()), 2)}


def run_flood_benchmark(messages: int = 100_000, rate: float = 50.0, quiet_s: float = 15.0, seed: int = 0,
                        rt_priority: int = 0, work: str = "runs/bench-flood", out: str | None = None) -> dict:
    """Measure the actor's loop before, during and after a flood (module docstring).

    :param messages: garbage messages in the flood
    :param rate: the actor's control rate (Hz)
    :param quiet_s: seconds measured before and after the flood
    :param seed: seed of the run
    :param rt_priority: run the actor's loop under SCHED_FIFO at this priority (0: normal scheduling)
    :param work: run directory
    :param out: also write the results as JSON here
    """
    from khgrl.benchmarks.runtime.procs import BenchProcs, run_id
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Frame
    from khgrl.common.wire.protocol import Keys, ProtocolError, decode

    work_dir = Path(work).resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    procs, run = BenchProcs(work_dir), run_id("flood")
    steps: list[tuple[int, int, float]] = []

    def on_frame(sample) -> None:
        try:
            f = decode(Frame, sample.payload.to_bytes())
        except ProtocolError:
            return
        steps.append((f.episode, f.t, f.envelope.ts))

    try:
        ep = procs.router()
        procs.learner("learner", run, ep, work_dir / run, "--learning-starts", "64", "--mode", "robot")
        procs.supervise(run, ep, work_dir / run)  # (robot mode: the actor moves only while supervised)
        rt = ["--actor-rt-priority", str(rt_priority)] if rt_priority else []
        actor = procs.actor("actor", run, ep, work_dir / run, "--episodes", "1000", "--rate", str(rate), "--mode",
                            "robot", "--seed", str(seed), *rt)
        with open_client(ep, timeout=30) as session:
            sub = session.declare_subscriber(Keys(run).frame("a0"), on_frame)
            while len(steps) < 50:
                if actor.poll() is not None:
                    raise RuntimeError(f"actor exited {actor.poll()}: {actor.tail()}")
                time.sleep(0.2)
            time.sleep(quiet_s)
            load0 = os.getloadavg()
            flood = subprocess.run([sys.executable, "-c", FLOOD, ep, run, str(messages)], cwd=REPO, text=True,
                                   capture_output=True, timeout=600, env={**os.environ, "PYTHONPATH": str(REPO)})
            f0, f1 = (float(x) for x in flood.stdout.split())
            time.sleep(quiet_s)
            sub.undeclare()
    finally:
        procs.close()
    summary = json.loads((work_dir / run / "actor-a0" / "summary.json").read_text())
    period = 1e3 / rate
    res = {"messages": messages, "rate_hz": rate, "period_ms": period, "rt_priority": rt_priority,
           "flood_s": round(f1 - f0, 2), "before": _stats(_periods(steps, f0 - quiet_s, f0)),
           "during": _stats(_periods(steps, f0, f1 + 0.5)), "after": _stats(_periods(steps, f1 + 0.5, f1 + quiet_s)),
           "actor_rejects": summary.get("rejects", {}), "actor_exit": summary.get("exit_code"),
           "load_before": [round(x, 2) for x in load0], "load_after": [round(x, 2) for x in os.getloadavg()],
           "cpus": os.cpu_count()}
    for k in ("before", "during", "after"):
        s = res[k]
        print(f"{k:>6}: {s.get('n', 0)} periods, p50 {s.get('p50')} ms, p99 {s.get('p99')} ms, max {s.get('max')} ms "
              f"(target {period:g} ms)")
    print(f"flood: {messages} messages in {res['flood_s']} s; actor rejects {res['actor_rejects']}; load "
          f"{res['load_before']}")
    if out:
        Path(out).write_text(json.dumps(res, indent=2))
        print(f"wrote {out}")
    return res
