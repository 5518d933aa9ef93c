"""Many actors into one learner (``khgrl bench scale``): the real ``khgrl up`` with N actors for a fixed time, then
Ctrl-C (a clean stop: the learner's final checkpoint), per case:

* **startup**: seconds from launch to the first batch the learner reports ingested (reported apart: each case
  then runs ``seconds`` from there, and its rates count from there);
* **ingest**: transitions per second the learner stored (from its status, from the first ingested batch on);
* **learner steps/s**: the learner's gradient steps per second over the same span, and whether the system is
  **learner-bound**: in simulation mode (UTD 1) the actors wait for the learner, so it is when the learner spends
  most of that span training (``learner_busy``: its training seconds, from its closing log line, over the span;
  ``learner_bound``: at least :data:`BOUND`; it can read a little over 1: the learner finishes its iteration
  after the Ctrl-C, and its first status comes up to a second after its first batch);
* **cores busy** by role (router, learner, actors, the rest): CPU seconds of the case's processes over the same
  span, per second (:mod:`~khgrl.benchmarks.proc_cpu`);
* **learner memory**: RSS over time (sampled from its status about once a second), the peak and the last value;
* **inbox depth**: messages waiting in the learner (peak);
* **update-to-data ratio** achieved (gradient steps per transition; simulation mode keeps the paper's 1);
* **weights latency** (publish -> applied in an actor's loop, p50/p99 over the actors) and the **actor loop
  period** p99 (each actor's ``summary.json``);
* **exactly once after Ctrl-C**: every transition an actor produced is in the learner's final checkpoint
  exactly once (provenance: actor code and running index), or was overwritten in a full replay buffer (then
  the buffer holds the newest ones once each) -- ``lost`` and ``duplicated`` must be 0.

Cases: N actors x rate (0: as fast as flow control allows; 50 Hz) x mode (simulation: actors wait for the
learner; robot: they never do). The machine's load average is recorded before and after each case.

    khgrl bench scale --actors 1 2 4 8 --rates 0 50 --modes simulation robot --seconds 60
    khgrl bench scale --actors 1 8 14 --rates 0 --modes simulation --device cuda

The children get the caller's environment, ``PYTHONPATH`` extended by the source tree (when run from one), not
replaced: packages installed with ``--target`` or a task module on the caller's path stay importable.
"""

from __future__ import annotations

import itertools
import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from khgrl.benchmarks.proc_cpu import cpu_between, tree_cpu
from khgrl.common.delivery.transport import free_port, open_client, wait_reachable
from khgrl.common.wire.protocol import Keys, Status, decode

__all__ = ["run_scale_benchmark", "provenance_check", "scale_case"]

REPO = Path(__file__).resolve().parents[1]
STARTUP_S = 180.0  # longest wait for the first ingested batch of a case
BOUND = 0.8  # the learner training this share of the time or more: the system is learner-bound
_CASES = itertools.count()  # run ids of one process's cases differ (a case may be measured twice)


def provenance_check(run_dir: Path) -> dict:
    """Compare what each actor produced (its ``summary.json``: running indices ``first_index..next_index``) with
    the learner's final checkpoint: transitions lost (produced, not stored, not legitimately overwritten) and
    duplicated (stored twice).

    :param run_dir: the run directory of a finished ``khgrl up``
    """
    from khgrl.learner.checkpoint import find_checkpoint, load_checkpoint_arrays

    ckpt = find_checkpoint(run_dir / "learner")
    arrays = load_checkpoint_arrays(ckpt)
    state = json.loads((ckpt / "state.json").read_text())
    codes = {a: int(s["code"]) for a, s in state.get("actors", {}).items()}
    actor_codes, steps = arrays["provenance_actor"], arrays["provenance_step"]
    full = bool(state.get("replay", {}).get("full"))
    lost = dup = produced = stored = 0
    for summary_file in sorted(run_dir.glob("actor-*/summary.json")):
        s = json.loads(summary_file.read_text())
        actor = summary_file.parent.name.removeprefix("actor-")
        n = int(s.get("next_index", s.get("transitions", 0)))
        produced += n
        held = steps[actor_codes == codes.get(actor, -2)]
        uniq = np.unique(held)
        dup += held.size - uniq.size
        stored += uniq.size
        lowest = 0 if not full else (int(uniq.min()) if uniq.size else n)  # a full buffer dropped the oldest
        lost += (n - lowest) - int(np.count_nonzero((uniq >= lowest) & (uniq < n)))
    return {"produced": produced, "stored": stored, "lost": lost, "duplicated": dup, "buffer_full": full}


def child_env() -> dict[str, str]:
    """The caller's environment for ``khgrl up``, ``PYTHONPATH`` extended (not replaced) by the source tree when this
    module runs from one (a wheel's install needs nothing added)."""
    env = dict(os.environ)
    if (REPO / "pyproject.toml").is_file():
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def scale_case(work: Path, actors: int, rate: float, mode: str, seconds: float, seed: int,
               secure: bool = False, device: str = "auto", extra: tuple[str, ...] = ()) -> dict:
    """One ``khgrl up`` for ``seconds`` from its first ingested batch, then Ctrl-C; its numbers (module docstring).

    :param secure: ``khgrl up --secure`` (mutual TLS and access control) instead of plain TCP
    :param device: the learner's ``--device``
    :param extra: more ``khgrl up`` flags (``khgrl bench images``: the task, no training)
    """
    port = free_port()
    run = f"scale{actors}r{int(rate)}{mode[0]}{'m' if secure else ''}{os.getpid()}-{next(_CASES)}"
    run_dir = work / run
    argv = [sys.executable, "-m", "khgrl.deploy.cli", "up", "--actors", str(actors), "--rate", str(rate),
            "--mode", mode,
            "--episodes", "1000000", "--human", "none", "--run", run, "--run-dir", str(run_dir), "--port", str(port),
            "--seed", str(seed), "--no-progress", "--device", device, *(["--secure"] if secure else []), *extra]
    ep = f"{'tls' if secure else 'tcp'}/127.0.0.1:{port}"
    load0 = os.getloadavg()
    samples: list[tuple[float, dict]] = []
    t_launch, first, cpu0 = time.monotonic(), None, {}
    source = (REPO / "pyproject.toml").is_file()
    proc = subprocess.Popen(argv, cwd=REPO if source else None, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True, env=child_env())
    try:
        wait_reachable(ep, 60.0)
        monitor = str(run_dir / "certs" / "zenoh" / "monitor.json5") if secure else None
        with open_client(ep, timeout=30, zenoh_config=monitor) as session:
            sub = session.declare_subscriber(Keys(run).status("learner"), lambda s: samples.append(
                (time.monotonic(), decode(Status, s.payload.to_bytes()).info)))
            t_end = time.monotonic() + STARTUP_S  # until the first ingested batch, then ``seconds`` from it
            while time.monotonic() < t_end and proc.poll() is None:
                time.sleep(0.2)
                if first is None and any(i.ingested > 0 for _, i in list(samples)):
                    first = next(t for t, i in list(samples) if i.ingested > 0)
                    t_end, cpu0 = first + seconds, tree_cpu(proc.pid)
            sub.undeclare()
    finally:
        t_stop = time.monotonic()
        cpu = cpu_between(cpu0, tree_cpu(proc.pid)) if first is not None else {}
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        rc = proc.wait(timeout=300)
    startup = (first - t_launch) if first is not None else float("nan")
    busy = _train_seconds(run_dir) / (t_stop - first) if first is not None else float("nan")
    return {"transport": "mtls" if secure else "tcp", "device": device, "startup_s": round(startup, 1),
            "learner_busy": round(busy, 2), "learner_bound": bool(busy >= BOUND),
            "cores_busy": {role: round(c / max(t_stop - first, 1e-9), 3) for role, c in cpu.items()},
            **_summarize(run_dir, samples, actors, rate, mode, rc, load0)}


def _train_seconds(run_dir: Path) -> float:
    """The learner's training seconds, from its closing log line (``train_s``; NaN if it has none)."""
    import re

    log = run_dir / "learner" / "learner.log"
    found = re.findall(r"'train_s': ([0-9.]+)", log.read_text(errors="replace")) if log.is_file() else []
    return float(found[-1]) if found else float("nan")


def _summarize(run_dir: Path, samples: list, actors: int, rate: float, mode: str, rc: int, load0) -> dict:
    infos = [(t, i) for t, i in samples]
    warm = [(t, i) for t, i in infos if i.ingested > 0]
    if len(warm) >= 2:
        (t0, a), (t1, b) = warm[0], warm[-1]  # from the first ingested batch on
        ingest = (b.ingested - a.ingested) / max(t1 - t0, 1e-9)
        steps = (b.gradient_steps - a.gradient_steps) / max(t1 - t0, 1e-9)
    else:
        ingest = steps = float("nan")
    rss = [i.rss_mb for _, i in infos]
    lat, loop = [], []
    for f in sorted(run_dir.glob("actor-*/summary.json")):
        s = json.loads(f.read_text())
        lat.append(s.get("weights_latency_ms", {}))
        loop.append(s.get("loop_period_ms", {}))
    pick = lambda ds, k: max((d[k] for d in ds if d.get(k) is not None), default=float("nan"))  # noqa: E731
    return {"actors": actors, "rate_hz": rate, "mode": mode, "exit_code": rc,
            "ingest_per_s": round(ingest, 1), "learner_steps_per_s": round(steps, 1),
            "rss_mb_peak": max(rss, default=float("nan")),
            "rss_mb_last": rss[-1] if rss else float("nan"),
            "rss_mb_series": [round(r, 1) for r in rss],
            "inbox_depth_peak": max((i.queue_depth for _, i in infos), default=0),
            "utd": infos[-1][1].utd if infos else float("nan"),
            "weights_latency_ms_p50": pick(lat, "p50"), "weights_latency_ms_p99": pick(lat, "p99"),
            "actor_loop_ms_p99": pick(loop, "p99"), **provenance_check(run_dir),
            "load_before": [round(x, 2) for x in load0], "load_after": [round(x, 2) for x in os.getloadavg()]}


def run_scale_benchmark(actors: tuple[int, ...] = (1, 2, 4, 8), rates: tuple[float, ...] = (0.0, 50.0),
                        modes: tuple[str, ...] = ("simulation", "robot"), seconds: float = 60.0, seed: int = 0,
                        work: str = "runs/bench-scale", out: str | None = None, device: str = "auto") -> list[dict]:
    """Run every case and print a table (and write JSON to ``out``).

    :param actors: actor counts
    :param rates: actor rates in Hz (0: as fast as possible)
    :param modes: simulation and/or robot
    :param seconds: how long each case runs before Ctrl-C
    :param seed: seed of the runs
    :param work: where the run directories go
    :param out: JSON file of the results
    :param device: the learner's ``--device`` (auto, cpu, cuda)
    """
    work_dir = Path(work).resolve()
    work_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for mode in modes:
        for rate in rates:
            for n in actors:
                r = scale_case(work_dir, n, rate, mode, seconds, seed, device=device)
                results.append(r)
                print(f"{mode:>10} {rate:>4g} Hz {n} actors: startup {r['startup_s']:.1f} s, then ingest "
                      f"{r['ingest_per_s']:>9.1f}/s, learner {r['learner_steps_per_s']:.1f} steps/s (busy "
                      f"{r['learner_busy']:.0%}: {'learner-bound' if r['learner_bound'] else 'not learner-bound'}), "
                      f"RSS peak "
                      f"{r['rss_mb_peak']:.0f} MB (last {r['rss_mb_last']:.0f}), inbox peak {r['inbox_depth_peak']}, "
                      f"UTD {r['utd']:.3f}, weights p50/p99 {r['weights_latency_ms_p50']:.1f}/"
                      f"{r['weights_latency_ms_p99']:.1f} ms, loop p99 {r['actor_loop_ms_p99']:.1f} ms, produced "
                      f"{r['produced']}, lost {r['lost']}, duplicated {r['duplicated']}", flush=True)
    if out:
        doc = {"machine": {"host": platform.node(), "cpus": os.cpu_count()}, "seconds": seconds, "device": device,
               "cases": results}
        Path(out).write_text(json.dumps(doc, indent=2))
        print(f"wrote {out}")
    return results
