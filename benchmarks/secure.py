"""What security costs (``khgrl bench secure``): mutual TLS + access control against plain TCP, in one run, on the
same machine, alternating so that both see the same load:

* **ingest**: ``khgrl bench ingest`` -- S sender processes into one learner that does not train, transitions/s
  acknowledged (the data path's ceiling, where the encryption's cost shows most);
* **weights latency** and **ingest of the real system**: ``khgrl up`` with N actors in robot mode at R Hz for a
  fixed time (``khgrl bench scale``'s case), weights latency p50/p99 (publish -> applied in an actor's loop),
  transitions/s stored, exactly once after Ctrl-C.

    khgrl bench secure --senders 8 --transitions 200000 --actors 2 --rate 50 --seconds 60 --out docs/bench_secure.json
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

__all__ = ["run_secure_benchmark"]


def run_secure_benchmark(senders: int = 8, transitions: int = 200_000, actors: int = 2, rate: float = 50.0,
                         seconds: float = 60.0, repeats: int = 2, seed: int = 0, work: str = "runs/bench-secure",
                         out: str | None = None) -> dict:
    """Each measurement plain and with mTLS, ``repeats`` times alternating; prints a table, returns (and writes)
    the numbers.

    :param senders: sender processes of the ingest measurement
    :param transitions: transitions in all per ingest measurement
    :param actors: actors of the ``khgrl up`` measurement
    :param rate: their rate in Hz
    :param seconds: length of each ``khgrl up`` measurement
    :param repeats: how often each pair is measured
    :param seed: seed
    :param work: where runs go
    :param out: JSON file of the results
    """
    from khgrl.benchmarks.ingest_many import run_ingest_benchmark
    from khgrl.benchmarks.scale import scale_case

    work_dir = Path(work).resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    ingest, system = [], []
    for _ in range(repeats):
        for secure in (False, True):
            ingest.append(run_ingest_benchmark(senders=senders, transitions=transitions, seed=seed,
                                               work=str(work_dir / "ingest"), secure=secure))
    for _ in range(repeats):
        for secure in (False, True):
            r = scale_case(work_dir / "up", actors, rate, "robot", seconds, seed, secure=secure)
            r.pop("rss_mb_series", None)
            system.append(r)
            print(f"{r['transport']}: khgrl up {actors} actors at {rate:g} Hz (robot mode) {seconds:g} s: ingest "
                  f"{r['ingest_per_s']:.1f}/s, weights latency p50/p99 {r['weights_latency_ms_p50']:.1f}/"
                  f"{r['weights_latency_ms_p99']:.1f} ms, produced {r['produced']}, lost {r['lost']}, "
                  f"duplicated {r['duplicated']}", flush=True)
    summary = _summary(ingest, system)
    for line in summary["lines"]:
        print(line)
    doc = {"machine": {"host": platform.node(), "cpus": os.cpu_count()}, "ingest": ingest, "system": system,
           "summary": summary}
    if out:
        Path(out).write_text(json.dumps(doc, indent=2))
        print(f"wrote {out}")
    return doc


def _mean(rows: list[dict], transport: str, key: str) -> float:
    vals = [float(r[key]) for r in rows if r["transport"] == transport]
    return sum(vals) / len(vals) if vals else float("nan")


def _summary(ingest: list[dict], system: list[dict]) -> dict:
    out = {}
    for name, rows, key in (("ingest_per_s", ingest, "transitions_per_s"), ("system_ingest_per_s", system,
                                                                            "ingest_per_s"),
                            ("weights_latency_ms_p50", system, "weights_latency_ms_p50"),
                            ("weights_latency_ms_p99", system, "weights_latency_ms_p99")):
        tcp, mtls = _mean(rows, "tcp", key), _mean(rows, "mtls", key)
        out[name] = {"tcp": round(tcp, 1), "mtls": round(mtls, 1), "ratio_mtls_to_tcp": round(mtls / tcp, 3)}
    out["lines"] = [f"{k}: tcp {v['tcp']}, mTLS {v['mtls']} (mTLS/tcp {v['ratio_mtls_to_tcp']})"
                    for k, v in out.items()]
    return out
