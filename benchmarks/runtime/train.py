"""Measurement 4: gradient steps per second of a learner with a backlog of due training iterations, next to a
standalone TQC training in this process, in alternating slices (the learner paused while this one trains)."""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np
from khgrl.benchmarks.runtime.link import Link, batches
from khgrl.benchmarks.runtime.procs import TRAIN_FREQ, BenchProcs, pct, run_id
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery.transport import open_client
from khgrl.common.tasks.spaces import ACT_DIM, OBS_DIM

__all__ = ["measure_train", "standalone_model"]

LEARNING_STARTS = 512


def standalone_model(seed: int, n_fill: int):
    """TQC with the paper's settings on the passage spaces; replay buffer filled with random transitions.

    :param seed: the model's seed
    :param n_fill: transitions in the buffer
    """
    import torch
    from khgrl.common.tasks.spaces import SpacesEnv
    from sb3_contrib import TQC
    from stable_baselines3.common.logger import Logger

    torch.set_num_threads(1)  # as the learner (--learner-threads 1) and the baseline
    model = TQC("MlpPolicy", SpacesEnv(), **TQCSettings().sb3_kwargs(seed))
    model.set_logger(Logger(folder=None, output_formats=[]))
    rb = model.replay_buffer
    rng = np.random.default_rng(seed)
    n = min(n_fill, rb.buffer_size)
    rb.observations[:n] = rng.random((n, 1, OBS_DIM), dtype=np.float32)
    rb.next_observations[:n] = rng.random((n, 1, OBS_DIM), dtype=np.float32)
    rb.actions[:n] = rng.uniform(-1, 1, (n, 1, ACT_DIM)).astype(np.float32)
    rb.rewards[:n] = rng.standard_normal((n, 1)).astype(np.float32)
    rb.dones[:n] = (rng.random((n, 1)) < 0.005).astype(np.float32)
    rb.pos, rb.full = n, False
    model.num_timesteps = n
    model.train(gradient_steps=TRAIN_FREQ, batch_size=model.batch_size)  # warm-up (the first call allocates)
    return model


def _time_train(model, seconds: float, min_calls: int = 3) -> list[float]:
    times = []
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end or len(times) < min_calls:
        t0 = time.perf_counter()
        model.train(gradient_steps=TRAIN_FREQ, batch_size=256)
        times.append(time.perf_counter() - t0)
    return times


def _until_paused(link: Link, timeout: float = 15.0) -> None:
    """The status after a pause (sent between iterations) says paused: nothing trains from then on."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(m.info.paused for m in link.statuses()):
            return
        time.sleep(0.05)
    raise RuntimeError("the learner did not report paused")


def _learner_slice(link: Link, slice_s: float, n: int) -> tuple[float, int, float, int]:
    """Let the paused learner train for ``slice_s`` s: (first ts, gradient steps, last ts, gradient steps)
    of the status messages sent while it trained from the backlog."""
    link.statuses()
    link.control("resume")
    seen: list[tuple[float, int]] = []
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < slice_s or len(seen) < 2:
        time.sleep(0.1)
        for m in link.statuses():
            info = m.info
            if not info.paused and info.ingested >= n and info.pending_iterations > 0:
                seen.append((float(m.envelope.ts), int(info.gradient_steps)))
        if time.perf_counter() - t0 > slice_s + 20:
            raise RuntimeError("learner: no status messages while training from the backlog")
    link.control("pause")
    _until_paused(link)
    return seen[0][0], seen[0][1], seen[-1][0], seen[-1][1]


def _iteration_times(run_dir: Path) -> list[float]:
    """The learner's own time inside ``model.train()`` per iteration (its ``learner/iteration_s`` scalar)."""
    out: list[float] = []
    path = run_dir / "learner" / "tb" / "progress.csv"
    if path.exists():
        with open(path) as fh:
            out = [float(row["learner/iteration_s"]) for row in csv.DictReader(fh) if row.get("learner/iteration_s")]
    return out


def measure_train(procs: BenchProcs, ep: str, work: Path, *, seconds: float, rounds: int, batch: int,
                  inflight: int, seed: int, report: Callable[[str, float], None]) -> dict:
    """Learner (backlog of due iterations) and standalone ``train()`` in alternating slices of
    ``seconds / rounds``.

    :param procs: the benchmark's processes
    :param ep: the router endpoint
    :param work: the work directory
    :param seconds: training time of each side
    :param rounds: slices of each side
    :param batch: transitions per published batch
    :param inflight: unacknowledged batches at most
    :param seed: seed
    :param report: ``report(what, fraction done)``
    """
    tag = "train"
    run = run_id(tag)
    # enough due iterations that the backlog outlasts the window even at 400 gradient steps/s
    n = LEARNING_STARTS + TRAIN_FREQ * math.ceil(seconds * 400 / TRAIN_FREQ)
    payloads = batches(n, batch, seed + 1)
    # at this process's priority: khgrl up runs the learner at nice 5 so that training yields the CPU to the actors,
    # but what is compared here is the code, not the priority (niced, any other load on the machine slows it alone)
    # the backlog is stored while the learner is paused: far more than any lead cap lets an actor have out, so the
    # cap is off here (--max-lead beyond the backlog) and the batch size is the one published
    learner = procs.learner(f"learner-{tag}", run, ep, work / tag, "--learning-starts", str(LEARNING_STARTS),
                            "--checkpoint-every", "0", "--model-checkpoint-every", "0", "--learner-nice", "0",
                            "--batch", str(batch), "--max-lead", str(2 * n))
    slice_s = seconds / rounds
    spans: list[tuple[float, int, float, int]] = []
    standalone: list[float] = []
    standalone_slices: list[float] = []
    try:
        report("standalone TQC: building", 0.0)
        model = standalone_model(seed, n)
        with open_client(ep) as session:
            link = Link(session, run)
            try:
                link.wait_learner(learner)
                report("learner: publishing the backlog (paused)", 0.02)
                link.control("pause")
                _until_paused(link)
                link.stream(payloads, inflight)
                for k in range(rounds):
                    report(f"round {k + 1}/{rounds}: standalone train()", (2 * k + 0.5) / (2 * rounds))
                    times = _time_train(model, slice_s)
                    standalone += times
                    standalone_slices.append(TRAIN_FREQ * len(times) / sum(times))
                    report(f"round {k + 1}/{rounds}: learner", (2 * k + 1.5) / (2 * rounds))
                    spans.append(_learner_slice(link, slice_s, n))
            finally:
                link.close()
        learner.stop(60.0)
    finally:
        learner.stop(30.0)
    return _train_record(spans, standalone, standalone_slices, _iteration_times(work / tag), rounds, n)


def _train_record(spans: list, standalone: list[float], standalone_slices: list[float], iteration_s: list[float],
                  rounds: int, n: int) -> dict:
    steps = sum(g1 - g0 for _, g0, _, g1 in spans)
    span_s = sum(t1 - t0 for t0, _, t1, _ in spans)
    learner_rate = steps / span_s
    standalone_rate = TRAIN_FREQ * len(standalone) / sum(standalone)
    med_it, med_sa = pct(iteration_s, 50), pct(standalone, 50)
    return {
        "learner_grad_steps_per_s": learner_rate,
        "learner_slices": [{"s": t1 - t0, "grad_steps": g1 - g0, "rate": (g1 - g0) / (t1 - t0)}
                           for t0, g0, t1, g1 in spans],
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
        "learning_starts": LEARNING_STARTS,
    }
