"""Runtime of the distributed system (``khgrl bench runtime``): what the Zenoh split costs and buys.

Every measurement runs real processes (a router, learners, actors: ``python -m deploy.cli ...`` subprocesses,
killed by PID at the end) on this machine, in ONE benchmark run, one after the other, so the ratios are taken
under the same load:

1. **ingest**: transitions per second a learner (``--learning-starts`` 10^9: it never trains) ingests from
   valid transition batches this process publishes as fast as the acks allow (at most ``inflight`` batches
   unacknowledged): total transitions / time from the first put to the ack of the last seq. Twice: without
   checkpoints and with the learner's default durability checkpoints (every 2000 transitions).
2. **weights latency**: an actor (``--rate 50 --max-lead 1000000``, so the lead limit never stops it) and a
   training learner; for every weights version the actor applies: time from the learner's publish (the
   message's ``ts``) to the swap in the actor's control loop (``weights_latency_ms`` of the actor's summary).
3. **control-loop period** of that same actor at 50 Hz while the learner trains, next to the gap between
   consecutive ``env.step`` calls of the single-process SB3 reference (``learner/reference.py``), which
   includes the 8-gradient-step update every 8 steps.
4. **gradient steps per second**: a learner with a backlog of due training iterations (transitions published
   by this process), from its status messages, next to a standalone TQC (``tqc_kwargs``, replay buffer of
   random transitions) timing ``model.train(gradient_steps=8, batch_size=256)`` in this process; the two
   alternate in slices (the learner is paused by a control message while this process trains, so they never
   compete for a core and a drifting load hits both alike); the ratio (target >= 90 %). Also reported: the
   learner's time inside ``train()`` alone (its ``learner/iteration_s`` scalar), which separates the service
   loop's overhead (weights publish, acks, logging) from a slower ``train()`` in that process.
5. **exactly-once across a learner kill** (optional, default on unless ``--quick``): an actor streams, the
   learner is SIGKILLed after its first checkpoint and restarted with ``--resume``; the final checkpoint's
   provenance is counted: transitions lost and duplicated.

Numbers on a small shared machine are noisy; the printed note says so and records the load average.
"""

from __future__ import annotations

import json
import math
import os
import platform
import queue
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["run_runtime_benchmark"]

REPO = Path(__file__).resolve().parents[1]
TRAIN_FREQ = 8
BENCH_ACTOR = "bench"


# ------------------------------------------------------------------------------------ processes
class _Proc:
    """One child process (new session, output in a log file); stopped by PID."""

    def __init__(self, name: str, argv: list[str], log_path: Path, env: dict) -> None:
        self.name = name
        self.log_path = log_path
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(log_path, "ab")
        self.popen = subprocess.Popen(argv, cwd=REPO, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                      start_new_session=True)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def poll(self) -> int | None:
        return self.popen.poll()

    def wait(self, timeout: float) -> int | None:
        try:
            return self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def _signal(self, sig: int) -> None:
        if self.popen.poll() is None:
            try:
                os.kill(self.popen.pid, sig)
            except ProcessLookupError:
                pass

    def kill(self) -> None:
        self._signal(signal.SIGKILL)
        self.wait(10)

    def stop(self, timeout: float = 20.0) -> int | None:
        """SIGTERM, wait, SIGKILL if still there."""
        self._signal(signal.SIGTERM)
        rc = self.wait(timeout)
        if rc is None:
            self.kill()
        return rc

    def text(self) -> str:
        try:
            self._log.flush()
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def tail(self, n: int = 30) -> str:
        return "\n".join(self.text().splitlines()[-n:])

    def close(self) -> None:
        if self.popen.poll() is None:
            self.stop(10.0)
        self._log.close()


class _Procs:
    def __init__(self, base: Path) -> None:
        self.base = base
        self.procs: list[_Proc] = []
        self.env = dict(os.environ)
        self.env["PYTHONPATH"] = str(REPO) + (os.pathsep + self.env["PYTHONPATH"] if self.env.get("PYTHONPATH") else "")
        self.env["PYTHONUNBUFFERED"] = "1"
        self.env.setdefault("RUST_LOG", "error")

    def start(self, name: str, command: str, args: list[str]) -> _Proc:
        argv = [sys.executable, "-m", "deploy.cli", command, *args]
        p = _Proc(name, argv, self.base / "logs" / f"{len(self.procs):02d}-{name}.log", self.env)
        self.procs.append(p)
        return p

    def close_all(self) -> None:
        for p in reversed(self.procs):
            try:
                p.close()
            except Exception:  # noqa: BLE001 - best effort on the way out
                pass


def _wait(cond: Callable[[], Any], timeout: float, what: str, procs: list[_Proc] = (), interval: float = 0.1) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        try:
            value = cond()
        except (OSError, ValueError, KeyError):
            value = None
        if value:
            return value
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"{p.name} exited with {p.poll()} while waiting for {what}; log {p.log_path}:\n{p.tail()}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(interval)


def _free_endpoint() -> str:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _start_router(procs: _Procs) -> str:
    ep = _free_endpoint()
    p = procs.start("router", "router", ["--listen", ep])
    host, port = ep.split("/", 1)[1].rsplit(":", 1)

    def up() -> bool:
        with socket.socket() as s:
            s.settimeout(0.3)
            return s.connect_ex((host, int(port))) == 0

    _wait(up, 30, f"router on {ep}", [p], interval=0.05)
    return ep


def _learner(procs: _Procs, name: str, run: str, ep: str, run_dir: Path, *extra: str) -> _Proc:
    return procs.start(name, "learner", ["--run", run, "--connect", ep, "--run-dir", str(run_dir), "--id", "learner",
                                         *extra])


def _wait_ready(p: _Proc, timeout: float = 120.0) -> None:
    _wait(lambda: " ready (epoch " in p.text(), timeout, f"{p.name} ready", [p], interval=0.1)


def _run_id(tag: str) -> str:
    return f"bench-{tag}-{secrets.token_hex(3)}"


def _pct(values, q) -> float | None:
    a = np.asarray(values, dtype=float)
    return float(np.percentile(a, q)) if a.size else None


def _load() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


# ------------------------------------------------------------------------------ transition stream
def _batches(n: int, batch: int, seed: int) -> list[bytes]:
    """``n`` valid transitions as encoded batches seq 0, 1, ... (encoded before timing starts)."""
    from common.protocol import ACT_DIM, OBS_DIM, encode

    rng = np.random.default_rng(seed)
    stream = secrets.token_hex(6)
    out = []
    for seq in range(math.ceil(n / batch)):
        m = min(batch, n - seq * batch)
        trunc = np.zeros(m, dtype=np.uint8)
        trunc[-1] = 1 if seq % 8 == 7 else 0  # an episode end now and then
        out.append(encode(
            "transitions", BENCH_ACTOR, seq, actor=BENCH_ACTOR, first_step=seq * batch,
            obs=rng.random((m, OBS_DIM), dtype=np.float32), next_obs=rng.random((m, OBS_DIM), dtype=np.float32),
            action=rng.uniform(-1, 1, (m, ACT_DIM)).astype(np.float32), reward=rng.standard_normal(m).astype(np.float32),
            terminated=np.zeros(m, dtype=np.uint8), truncated=trunc, intervened=np.zeros(m, dtype=np.uint8),
            clipped=np.zeros(m, dtype=np.uint8), stream=stream, base_seq=0))
    return out


class _Link:
    """This process's Zenoh client for one measurement: publishes transitions, collects acks and status."""

    def __init__(self, session, run: str) -> None:
        import zenoh

        from common.protocol import Keys

        self.session = session
        self.keys = Keys(run)
        self.acks: queue.Queue = queue.Queue()
        self.status: queue.Queue = queue.Queue()
        self.decls = [
            session.declare_subscriber(self.keys.ack(BENCH_ACTOR),
                                       lambda s: self.acks.put((time.perf_counter(), s.payload.to_bytes()))),
            session.declare_subscriber(self.keys.status("learner", "*"),
                                       lambda s: self.status.put((time.perf_counter(), s.payload.to_bytes()))),
        ]
        self.pub = session.declare_publisher(self.keys.transitions(BENCH_ACTOR),
                                             congestion_control=zenoh.CongestionControl.BLOCK,
                                             priority=zenoh.Priority.DATA)
        self.decls.append(self.pub)

    def wait_learner(self, timeout: float = 30.0) -> None:
        """Until the learner's liveliness token (declared after its subscribers) is visible here."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            replies = list(self.session.liveliness().get(self.keys.alive("learner", "*"), timeout=1.0))
            if any(r.ok for r in replies):
                time.sleep(0.3)  # let the subscription reach this client through the router
                return
            time.sleep(0.2)
        raise RuntimeError("the learner's liveliness token never appeared")

    def stream(self, payloads: list[bytes], inflight: int, on_progress: Callable[[int], None] | None = None,
               timeout: float = 300.0, stall_s: float = 5.0) -> dict:
        """Publish ``payloads`` keeping at most ``inflight`` unacknowledged; until the last seq is acked."""
        from common.protocol import ProtocolError, decode

        last = len(payloads) - 1
        received, nxt, resends = -1, 0, 0
        t0 = time.perf_counter()
        t_last = last_progress = t0
        while received < last:
            while nxt <= last and nxt - 1 - received < inflight:
                self.pub.put(payloads[nxt])
                nxt += 1
            block = True
            while True:
                try:
                    t, blob = self.acks.get(timeout=0.5) if block else self.acks.get_nowait()
                except queue.Empty:
                    break
                block = False
                try:
                    msg = decode("ack", blob)
                except ProtocolError:
                    continue
                if msg["received"] > received:
                    received, t_last = msg["received"], t
                    last_progress = time.perf_counter()
            if on_progress is not None:
                on_progress(received + 1)
            now = time.perf_counter()
            if now - t0 > timeout:
                raise RuntimeError(f"ingest: only seq {received} of {last} acknowledged after {timeout:.0f} s")
            if now - last_progress > stall_s:  # a lost batch (e.g. before the subscription was matched): re-send
                for s in range(received + 1, nxt):
                    self.pub.put(payloads[s])
                resends += 1
                last_progress = now
        return {"elapsed_s": t_last - t0, "resends": resends, "batches": len(payloads)}

    def statuses(self) -> list[tuple[float, dict]]:
        from common.protocol import ProtocolError, decode

        out = []
        while True:
            try:
                t, blob = self.status.get_nowait()
            except queue.Empty:
                return out
            try:
                out.append((t, decode("status", blob)))
            except ProtocolError:
                pass

    def close(self) -> None:
        for d in self.decls:
            try:
                d.undeclare()
            except Exception:  # noqa: BLE001
                pass


# --------------------------------------------------------------------------------- measurements
def _measure_ingest(procs: _Procs, ep: str, work: Path, *, n: int, batch: int, inflight: int, checkpoint_every: int,
                    seed: int, report: Callable) -> dict:
    from common.session import open_client

    tag = f"ingest-ckpt{checkpoint_every}"
    run = _run_id(tag)
    payloads = _batches(n, batch, seed)
    learner = _learner(procs, f"learner-{tag}", run, ep, work / tag, "--learning-starts", str(10**9),
                       "--checkpoint-every", str(checkpoint_every))
    try:
        _wait_ready(learner)
        with open_client(ep) as session:
            link = _Link(session, run)
            try:
                link.wait_learner()
                res = link.stream(payloads, inflight, on_progress=lambda k: report(k * batch, n))
                # the learner's own count (status every ~1 s)
                seen = _wait(lambda: [m for _, m in link.statuses() if m["info"]["ingested"] >= n], 5.0,
                             "learner status", [learner])
                info = seen[-1]["info"]
            finally:
                link.close()
    finally:
        learner.stop(30.0)
    rate = n / res["elapsed_s"]
    return {"transitions": n, "batch": batch, "inflight": inflight, "checkpoint_every": checkpoint_every,
            "elapsed_s": res["elapsed_s"], "transitions_per_s": rate, "resends": res["resends"],
            "learner_ingested": info["ingested"], "learner_duplicates": info["duplicates"].get(BENCH_ACTOR, 0),
            "learner_checkpoints": info["checkpoints"], "learner_iterations": info["iterations"]}


def _standalone_model(seed: int, n_fill: int):
    """TQC with the paper's settings on the passage spaces; replay buffer filled with random transitions."""
    import torch
    from sb3_contrib import TQC
    from stable_baselines3.common.logger import Logger

    from learner.reference import tqc_kwargs
    from learner.service import SpacesEnv

    torch.set_num_threads(1)  # as the learner (--threads 1) and the reference
    model = TQC("MlpPolicy", SpacesEnv(), **tqc_kwargs(seed))
    model.set_logger(Logger(folder=None, output_formats=[]))
    model._current_progress_remaining = 1.0
    rb = model.replay_buffer
    rng = np.random.default_rng(seed)
    n = min(n_fill, rb.buffer_size)
    rb.observations[:n] = rng.random((n, 1, 5), dtype=np.float32)
    rb.next_observations[:n] = rng.random((n, 1, 5), dtype=np.float32)
    rb.actions[:n] = rng.uniform(-1, 1, (n, 1, 2)).astype(np.float32)
    rb.rewards[:n] = rng.standard_normal((n, 1)).astype(np.float32)
    rb.dones[:n] = (rng.random((n, 1)) < 0.005).astype(np.float32)
    rb.pos, rb.full = n, False
    model.num_timesteps = n
    model.train(gradient_steps=TRAIN_FREQ, batch_size=model.batch_size)  # warm-up (first call allocates)
    return model


def _time_train(model, seconds: float, min_calls: int = 3) -> list[float]:
    times = []
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end or len(times) < min_calls:
        t0 = time.perf_counter()
        model.train(gradient_steps=TRAIN_FREQ, batch_size=256)
        times.append(time.perf_counter() - t0)
    return times


def _measure_train(procs: _Procs, ep: str, work: Path, *, seconds: float, rounds: int, batch: int, inflight: int,
                   seed: int, report: Callable) -> dict:
    """Learner (backlog of due iterations) and standalone train() in alternating slices of ``seconds / rounds``:
    the learner is paused (control message) while this process trains, so they never compete for a core and
    a drifting machine load hits both alike."""
    import csv

    from common.protocol import encode
    from common.session import open_client

    tag = "train"
    run = _run_id(tag)
    learning_starts = 512
    # enough due iterations that the backlog outlasts the window even at 400 gradient steps/s
    n = learning_starts + TRAIN_FREQ * math.ceil(seconds * 400 / TRAIN_FREQ)
    payloads = _batches(n, batch, seed + 1)
    learner = _learner(procs, f"learner-{tag}", run, ep, work / tag, "--learning-starts", str(learning_starts),
                       "--checkpoint-every", "0")
    slice_s = seconds / rounds
    spans: list[tuple[float, int, float, int]] = []  # per learner slice: first/last status (ts, gradient steps)
    standalone: list[float] = []
    standalone_slices: list[float] = []
    try:
        report("standalone TQC: building", 0.0)
        model = _standalone_model(seed, n)
        _wait_ready(learner)
        with open_client(ep) as session:
            link = _Link(session, run)
            ctl_seq = 0

            def control(command: str) -> None:
                nonlocal ctl_seq
                session.put(link.keys.control("learner"), encode("control", "bench", ctl_seq, command=command))
                ctl_seq += 1

            def until_paused(timeout: float = 15.0) -> None:
                # the status after the pause (sent between iterations) says paused: nothing trains from then on
                deadline = time.monotonic() + timeout
                while time.monotonic() < deadline:
                    if any(m["info"]["paused"] for _, m in link.statuses()):
                        return
                    time.sleep(0.05)
                raise RuntimeError("the learner did not report paused")

            try:
                link.wait_learner()
                report("learner: publishing the backlog (paused)", 0.02)
                control("pause")
                until_paused()
                link.stream(payloads, inflight)
                for k in range(rounds):
                    report(f"round {k + 1}/{rounds}: standalone train()", (2 * k + 0.5) / (2 * rounds))
                    times = _time_train(model, slice_s)
                    standalone += times
                    standalone_slices.append(TRAIN_FREQ * len(times) / sum(times))
                    report(f"round {k + 1}/{rounds}: learner", (2 * k + 1.5) / (2 * rounds))
                    link.statuses()
                    control("resume")
                    seen: list[tuple[float, int]] = []
                    t0 = time.perf_counter()
                    while time.perf_counter() - t0 < slice_s or len(seen) < 2:
                        time.sleep(0.1)
                        for _, m in link.statuses():
                            info = m["info"]
                            if not info["paused"] and info["ingested"] >= n and info["pending_iterations"] > 0:
                                seen.append((float(m["ts"]), int(info["gradient_steps"])))
                        if time.perf_counter() - t0 > slice_s + 20:
                            raise RuntimeError("learner: no status messages while training from the backlog")
                    control("pause")
                    until_paused()
                    spans.append((seen[0][0], seen[0][1], seen[-1][0], seen[-1][1]))
            finally:
                link.close()
        learner.stop(60.0)
    finally:
        learner.stop(30.0)
    steps = sum(g1 - g0 for _, g0, _, g1 in spans)
    span_s = sum(t1 - t0 for t0, _, t1, _ in spans)
    learner_rate = steps / span_s
    standalone_rate = TRAIN_FREQ * len(standalone) / sum(standalone)
    # the learner's own time inside model.train() per iteration (CSV/TensorBoard scalar learner/iteration_s)
    iteration_s = []
    csv_path = work / tag / "learner" / "tb" / "progress.csv"
    if csv_path.exists():
        with open(csv_path) as fh:
            for row in csv.DictReader(fh):
                if row.get("learner/iteration_s"):
                    iteration_s.append(float(row["learner/iteration_s"]))
    med_it, med_sa = _pct(iteration_s, 50), _pct(standalone, 50)
    return {
        "learner_grad_steps_per_s": learner_rate,
        "learner_slices": [{"s": t1 - t0, "grad_steps": g1 - g0, "rate": (g1 - g0) / (t1 - t0)} for t0, g0, t1, g1 in spans],
        "learner_window_s": span_s,
        "learner_window_grad_steps": steps,
        # median train() call (8 gradient steps), learner process vs this process
        "learner_train_call_grad_steps_per_s": TRAIN_FREQ / med_it if med_it else None,
        "learner_iteration_s_p50": med_it,
        "learner_iterations": len(iteration_s),
        "standalone_train_call_grad_steps_per_s": TRAIN_FREQ / med_sa,
        "standalone_grad_steps_per_s": standalone_rate,
        "standalone_slices": standalone_slices,
        "standalone_train_calls": len(standalone),
        "standalone_train_call_s_p50": med_sa,
        "ratio": learner_rate / standalone_rate,
        "rounds": rounds,
        "backlog_transitions": n,
        "learning_starts": learning_starts,
    }


def _episodes_logged(p: _Proc) -> int:
    return sum(1 for line in p.text().splitlines() if "khgrl.actor INFO episode " in line)


def _measure_actor(procs: _Procs, ep: str, work: Path, *, scenario: str, episodes: int, rate: float, seed: int,
                   report: Callable, rt_priority: int = 0) -> dict:
    tag = "actor-rt" if rt_priority else "actor"
    run = _run_id(tag)
    run_dir = work / tag
    learning_starts = 128
    # as `khgrl up` does: the learner runs at nice 5 so training yields the CPU to the control loop
    learner = _learner(procs, f"learner-{tag}", run, ep, run_dir, "--learning-starts", str(learning_starts),
                       "--seed", str(seed), "--nice", "5")
    actor = procs.start("actor", "actor", [
        "--run", run, "--connect", ep, "--run-dir", str(run_dir), "--id", "a0", "--scenario", scenario,
        "--method", "kgrl", "--episodes", str(episodes), "--seed", str(seed), "--rate", str(rate),
        "--max-lead", "1000000", "--learning-starts", str(learning_starts),
        *(["--rt-priority", str(rt_priority)] if rt_priority else [])])
    try:
        deadline = time.monotonic() + 120 + episodes * 60
        while actor.poll() is None:
            if learner.poll() is not None:
                raise RuntimeError(f"learner exited with {learner.poll()}:\n{learner.tail()}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"actor did not finish in time:\n{actor.tail()}")
            report(_episodes_logged(actor), episodes)
            time.sleep(0.5)
        if actor.poll() != 0:
            raise RuntimeError(f"actor exited with {actor.poll()}:\n{actor.tail()}")
        learner.stop(60.0)
    finally:
        learner.stop(30.0)
        actor.stop(30.0)
    summary = json.loads((run_dir / "actor-a0" / "summary.json").read_text())
    state = json.loads((run_dir / "learner" / "checkpoint" / "state.json").read_text())
    return {
        "scenario": scenario, "episodes": summary["episodes"], "transitions": summary["transitions"],
        "rate_hz": rate, "loop_period_ms": summary["loop_period_ms"],
        "weights_latency_ms": summary["weights_latency_ms"],
        "weights_applied": summary["weights"]["swaps"], "weights_received": summary["weights"]["received"],
        "weights_versions_published": state["version"],
        "rate_limit": summary["rate_limit"],
        "learner_iterations": state["iterations"], "learner_gradient_steps": state["gradient_steps"],
        "learner_pending_iterations_at_end": len(state["due"]),
        "actor_wall_s": summary["wall_time_s"], "realtime": summary.get("realtime", False),
    }


def _measure_reference(work: Path, *, scenario: str, episodes: int, seed: int) -> dict:
    from learner.reference import ReferenceConfig, run_reference

    run_dir = work / "reference"
    t0 = time.perf_counter()
    run_reference(ReferenceConfig(scenario=scenario, method="kgrl", episodes=episodes, seed=seed), run_dir,
                  progress=False)
    summary = json.loads((run_dir / "summary.json").read_text())
    return {"scenario": scenario, "method": "kgrl", "episodes": episodes, "env_steps": summary["env_steps"],
            "gradient_steps": summary["gradient_steps"], "step_gap_ms": summary["step_gap_ms"],
            "learn_wall_s": summary["wall_time_s"], "total_s": time.perf_counter() - t0}


def _measure_kill_resume(procs: _Procs, ep: str, work: Path, *, seed: int, report: Callable) -> dict:
    from learner.service import load_checkpoint_arrays

    tag = "resume"
    run = _run_id(tag)
    run_dir = work / tag
    state_file = run_dir / "learner" / "checkpoint" / "state.json"
    largs = ["--learning-starts", "16", "--checkpoint-every", "64"]
    learner = _learner(procs, "learner-resume-1", run, ep, run_dir, *largs)
    actor = procs.start("actor-resume", "actor", [
        "--run", run, "--connect", ep, "--run-dir", str(run_dir), "--id", "a0", "--scenario", "low_cov",
        "--method", "kgrl", "--episodes", "2", "--seed", str(seed), "--rate", "120", "--max-lead", "100000",
        "--learning-starts", "16"])
    try:
        report("waiting for the learner's first checkpoint")
        _wait(lambda: json.loads(state_file.read_text())["total_ingested"] >= 128, 180, "a first checkpoint",
              [learner, actor])
        learner.kill()
        killed_at = json.loads(state_file.read_text())["total_ingested"]
        time.sleep(0.5)
        report(f"learner killed at {killed_at} checkpointed transitions; resuming")
        learner = _learner(procs, "learner-resume-2", run, ep, run_dir, *largs, "--resume")
        if actor.wait(240) != 0:
            raise RuntimeError(f"actor exited with {actor.poll()}:\n{actor.tail()}")
        learner.stop(60.0)
    finally:
        learner.stop(30.0)
        actor.stop(30.0)
    summary = json.loads((run_dir / "actor-a0" / "summary.json").read_text())
    ck = run_dir / "learner" / "checkpoint"
    state = json.loads((ck / "state.json").read_text())
    arrays = load_checkpoint_arrays(ck)
    pos = state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]
    codes, steps = arrays["provenance_actor"][:pos], arrays["provenance_step"][:pos]
    mine = [c for c, e in enumerate(state["codes"]) if e["actor"] == "a0"]
    got = steps[np.isin(codes, mine)]
    n = int(summary["transitions"])
    unique = set(got.tolist())
    return {
        "actor_transitions": n, "in_buffer": int(got.size), "killed_at_checkpointed": killed_at,
        "lost": len(set(range(n)) - unique), "duplicated": int(got.size - len(unique)),
        "unexpected": len(unique - set(range(n))), "actor_resends": summary["resends"],
        "actor_unconfirmed": summary["unconfirmed_transitions"],
    }


# ------------------------------------------------------------------------------------- the run
def _ms3(d: dict | None) -> str:
    if not d or d.get("p50") is None:
        return "-"
    return f"{d['p50']:.1f} / {d['p99']:.1f} / {d['max']:.1f} ms"


def run_runtime_benchmark(*, quick: bool = False, out: str | None = None, episodes: int | None = None,
                          actor_episodes: int | None = None, ingest_transitions: int | None = None,
                          ingest_checkpoint_transitions: int | None = None, batch: int = 256, inflight: int = 8,
                          train_seconds: float | None = None, rate: float = 50.0, scenario: str = "high_cov",
                          loss_check: bool | None = None, seed: int = 0, keep: bool = False, rt_priority: int = 20) -> dict:
    """Run the measurements (module docstring), print a table, write JSON to ``out``; returns the record."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
    from rich.table import Table

    episodes = episodes if episodes is not None else (1 if quick else 2)
    actor_episodes = actor_episodes if actor_episodes is not None else (2 if quick else 10)
    ingest_transitions = ingest_transitions if ingest_transitions is not None else (50_000 if quick else 200_000)
    ingest_ckpt_n = (ingest_checkpoint_transitions if ingest_checkpoint_transitions is not None
                     else (20_000 if quick else 100_000))
    train_seconds = train_seconds if train_seconds is not None else (10.0 if quick else 30.0)
    loss_check = (not quick) if loss_check is None else loss_check
    rounds = 2 if quick else 3
    if batch < 1 or batch > 4096 or inflight < 1 or episodes < 1 or actor_episodes < 1 or rate <= 0:
        raise ValueError("--batch in [1, 4096], --inflight, --episodes, --actor-episodes and --rate must be positive")

    console = Console(width=None if sys.stdout.isatty() else 150)
    work = Path(tempfile.mkdtemp(prefix="khgrl-bench-runtime-"))
    config = {"quick": quick, "episodes": episodes, "actor_episodes": actor_episodes,
              "ingest_transitions": ingest_transitions, "ingest_checkpoint_transitions": ingest_ckpt_n, "batch": batch,
              "inflight": inflight, "train_seconds": train_seconds, "train_rounds": rounds, "rate_hz": rate, "scenario": scenario,
              "loss_check": loss_check, "seed": seed, "rt_priority": rt_priority}
    machine = {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
               "load_start": _load()}
    console.print(f"[bold]KhGRL runtime benchmark[/] ({'quick' if quick else 'default'} sizes; {os.cpu_count()} CPUs, "
                  f"load average {machine['load_start']}); work dir {work}")
    record: dict[str, Any] = {"config": config, "machine": machine, "results": {}, "load": {}}
    results = record["results"]
    procs = _Procs(work)
    t_start = time.perf_counter()
    ok = False
    stages = (["ingest", "ingest_ckpt", "train", "actor"] + (["actor_rt"] if rt_priority else []) + ["reference"]
              + (["kill_resume"] if loss_check else []))
    progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                        TimeElapsedColumn(), console=console, transient=False)
    try:
        with progress:
            overall = progress.add_task("[bold]overall", total=len(stages), info="")

            def stage(name: str, description: str, total: float = 1.0):
                record["load"][name] = _load()
                return progress.add_task(description, total=total, info="")

            # 1. ingest
            task = stage("router", "router", 1)
            ep = _start_router(procs)
            progress.update(task, completed=1, info=ep)
            for key, n, every in (("ingest", ingest_transitions, 0), ("ingest_ckpt", ingest_ckpt_n, 2000)):
                task = stage(key, f"1. ingest {n} transitions (checkpoint every {every or 'never'})", n)
                res = _measure_ingest(procs, ep, work, n=n, batch=batch, inflight=inflight, checkpoint_every=every,
                                      seed=seed, report=lambda k, n_, t=task: progress.update(t, completed=k, info=f"{k}/{n_}"))
                results[key] = res
                progress.update(task, completed=n, info=f"{res['transitions_per_s']:,.0f} transitions/s")
                progress.advance(overall)

            # 4. gradient steps per second
            task = stage("train", f"4. learner vs standalone train() ({train_seconds:.0f} s each, {rounds} rounds)", 1.0)
            res = _measure_train(procs, ep, work, seconds=train_seconds, rounds=rounds, batch=batch, inflight=inflight, seed=seed,
                                 report=lambda what, frac, t=task: progress.update(t, completed=frac, info=what))
            results["train"] = res
            progress.update(task, completed=1.0, info=f"{res['learner_grad_steps_per_s']:.1f} vs "
                                                       f"{res['standalone_grad_steps_per_s']:.1f} gradient steps/s")
            progress.advance(overall)

            # 2 + 3. actor at 50 Hz with a training learner
            task = stage("actor", f"2+3. actor at {rate:g} Hz, {actor_episodes} episode(s), learner training",
                         actor_episodes)
            res = _measure_actor(procs, ep, work, scenario=scenario, episodes=actor_episodes, rate=rate, seed=seed,
                                 report=lambda k, n_, t=task: progress.update(t, completed=k, info=f"episode {k}/{n_}"))
            results["actor"] = res
            progress.update(task, completed=actor_episodes, info=f"period {_ms3(res['loop_period_ms'])}")
            progress.advance(overall)

            # 3b. the same actor with its control loop under SCHED_FIFO (as robot control loops run)
            if rt_priority:
                task = stage("actor_rt", f"3b. actor at {rate:g} Hz under SCHED_FIFO {rt_priority}, learner training",
                             actor_episodes)
                res = _measure_actor(procs, ep, work, scenario=scenario, episodes=actor_episodes, rate=rate, seed=seed,
                                     rt_priority=rt_priority,
                                     report=lambda k, n_, t=task: progress.update(t, completed=k, info=f"episode {k}/{n_}"))
                results["actor_rt"] = res
                progress.update(task, completed=actor_episodes, info=f"period {_ms3(res['loop_period_ms'])}"
                                + ("" if res["realtime"] else " (SCHED_FIFO refused: normal scheduling)"))
                progress.advance(overall)

            # 3. single-process reference
            task = stage("reference", f"3. single-process SB3 reference, {episodes} episode(s)", 1)
            res = _measure_reference(work, scenario=scenario, episodes=episodes, seed=seed)
            results["reference"] = res
            progress.update(task, completed=1, info=f"step gap {_ms3(res['step_gap_ms'])}")
            progress.advance(overall)

            # 5. exactly-once across a learner kill
            if loss_check:
                task = stage("kill_resume", "5. learner SIGKILL + --resume, exactly-once check", 1)
                res = _measure_kill_resume(procs, ep, work, seed=seed,
                                           report=lambda what, t=task: progress.update(t, info=what))
                results["kill_resume"] = res
                progress.update(task, completed=1, info=f"lost {res['lost']}, duplicated {res['duplicated']}")
                progress.advance(overall)
        ok = True
    finally:
        procs.close_all()
        if ok and not keep:
            shutil.rmtree(work, ignore_errors=True)
        elif not ok:
            console.print(f"[red]benchmark failed[/]: logs kept in {work / 'logs'}")
    machine["load_end"] = _load()
    record["wall_s"] = time.perf_counter() - t_start
    record["work_dir"] = str(work) if keep else None

    # ------------------------------------------------------------------ table
    r = results
    table = Table(title="KhGRL runtime (one run, same machine)")
    table.add_column("measurement")
    table.add_column("value", justify="right")
    table.add_column("compared with", justify="right")
    table.add_column("ratio / note")
    ing, ingc = r["ingest"], r["ingest_ckpt"]
    table.add_row("1. learner ingest, no checkpoints", f"{ing['transitions_per_s']:,.0f} transitions/s", "",
                  f"{ing['transitions']} in {ing['elapsed_s']:.2f} s, batches of {batch}, ≤ {inflight} unacked")
    table.add_row("1. learner ingest, checkpoint every 2000", f"{ingc['transitions_per_s']:,.0f} transitions/s",
                  f"{ing['transitions_per_s']:,.0f} /s",
                  f"{ingc['transitions_per_s'] / ing['transitions_per_s']:.0%} ({ingc['learner_checkpoints']} checkpoints)")
    act, ref = r["actor"], r["reference"]
    wl = act["weights_latency_ms"]
    table.add_row("2. weights publish → applied by actor (p50/p99/max)", _ms3(wl), "",
                  f"{wl['n']} of {act['weights_versions_published']} versions applied (newest wins)")
    lp = act["loop_period_ms"]
    table.add_row(f"3. actor loop period @ {rate:g} Hz (p50/p99/max)", _ms3(lp), f"target {1e3 / rate:.1f} ms",
                  f"{lp['n']} steps; learner trained {act['learner_gradient_steps']} gradient steps meanwhile")
    if "actor_rt" in r:
        rt = r["actor_rt"]
        lpr = rt["loop_period_ms"]
        table.add_row(f"3b. … control loop under SCHED_FIFO {rt_priority} (p50/p99/max)", _ms3(lpr),
                      f"target {1e3 / rate:.1f} ms",
                      (f"p99 {lpr['p99'] - 1e3 / rate:+.1f} ms from target (target ≤ +2 ms: "
                       f"{'met' if lpr['p99'] - 1e3 / rate <= 2.0 else 'NOT met'})") if rt["realtime"]
                      else "SCHED_FIFO refused (not root / no CAP_SYS_NICE): normal scheduling")
    gap = ref["step_gap_ms"]
    table.add_row("3. single-process SB3: env.step gap (p50/p99/max)", _ms3(gap), "",
                  f"pause p99 {gap['p99']:.0f} ms vs actor period p99 {lp['p99']:.1f} ms "
                  f"({gap['p99'] / lp['p99']:.1f}×)")
    tr = r["train"]
    table.add_row("4. learner gradient steps/s (backlog)", f"{tr['learner_grad_steps_per_s']:.1f} /s",
                  f"{tr['standalone_grad_steps_per_s']:.1f} /s standalone",
                  f"{tr['ratio']:.0%} (target ≥ 90 %: {'met' if tr['ratio'] >= 0.9 else 'NOT met'})")
    if tr["learner_train_call_grad_steps_per_s"]:
        lc, sc = tr["learner_train_call_grad_steps_per_s"], tr["standalone_train_call_grad_steps_per_s"]
        table.add_row("4. … median train() call alone (8 steps)", f"{lc:.1f} /s", f"{sc:.1f} /s standalone",
                      f"{lc / sc:.0%} (without the loop: weights publish, acks, logging)")
    if "kill_resume" in r:
        kr = r["kill_resume"]
        table.add_row("5. learner SIGKILL + resume", f"{kr['lost']} lost, {kr['duplicated']} duplicated",
                      f"{kr['actor_transitions']} transitions",
                      f"killed after {kr['killed_at_checkpointed']} checkpointed; {kr['actor_resends']} re-sends")
    console.print(table)
    note = (f"Machine: {os.cpu_count()} CPUs shared with other jobs; load average (1/5/15 min) "
            f"{machine['load_start']} at start, {machine['load_end']} at end. Absolute numbers are noisy; each ratio "
            f"compares values measured in this one run, minutes apart, under the same load. Wall time {record['wall_s']:.0f} s.")
    record["note"] = note
    console.print(note)
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(record, indent=2))
        console.print(f"wrote {out}")
    return record
