"""Measurements 2 and 3: an actor at a fixed control rate beside a training learner (weights latency, loop
period), and the single-process SB3 baseline's step gap for comparison."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

from khgrl.benchmarks.runtime.procs import BenchProcs, run_id

__all__ = ["measure_actor", "measure_reference"]


def _episodes_done(run_dir: Path) -> int:
    """Rows of the actor's episodes.csv so far."""
    try:
        return max(0, len((run_dir / "actor-a0" / "episodes.csv").read_text().splitlines()) - 1)
    except OSError:
        return 0


def measure_actor(procs: BenchProcs, ep: str, work: Path, *, scenario: str, episodes: int, rate: float, seed: int,
                  report: Callable[[int, int], None], rt_priority: int = 0) -> dict:
    """Actor ``a0`` (KGRL, ``rate`` Hz, no lead limit) with a training learner until it has run ``episodes``.

    :param procs: the benchmark's processes
    :param ep: the router endpoint
    :param work: the work directory
    :param scenario: the passage-world scenario
    :param episodes: episodes of the actor
    :param rate: control rate in Hz
    :param seed: seed of learner and actor
    :param report: ``report(episodes done, episodes)``
    :param rt_priority: SCHED_FIFO priority of the control loop (0: normal scheduling)
    """
    tag = "actor-rt" if rt_priority else "actor"
    run = run_id(tag)
    run_dir = work / tag
    # the lead limit off on both sides: the actor never waits and the learner stores all it sends (the learner's
    # default lead cap, 24 transitions, would defer what a 50 Hz actor sends ahead of training)
    common = ["--learning-starts", "128", "--seed", str(seed), "--max-lead", "1000000"]
    # as khgrl up does: the learner at nice 5, so training yields the CPU to the control loop
    learner = procs.learner(f"learner-{tag}", run, ep, run_dir, *common, "--learner-nice", "5")
    actor = procs.actor(tag, run, ep, run_dir, *common, "--scenario", scenario, "--method", "kgrl",
                        "--episodes", str(episodes), "--rate", str(rate),
                        *(["--actor-rt-priority", str(rt_priority)] if rt_priority else []))
    try:
        deadline = time.monotonic() + 120 + episodes * 60
        while actor.poll() is None:
            if learner.poll() is not None:
                raise RuntimeError(f"learner exited with {learner.poll()}:\n{learner.tail()}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"actor did not finish in time:\n{actor.tail()}")
            report(_episodes_done(run_dir), episodes)
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


def measure_reference(work: Path, *, scenario: str, episodes: int, seed: int) -> dict:
    """The single-process SB3 baseline (KGRL): its ``env.step`` gap, which includes the training pauses.

    :param work: the work directory
    :param scenario: the passage-world scenario
    :param episodes: episodes
    :param seed: seed
    """
    from khgrl.learner.baseline import ReferenceConfig, run_reference

    run_dir = work / "reference"
    t0 = time.perf_counter()
    run_reference(ReferenceConfig(scenario=scenario, method="kgrl", episodes=episodes, seed=seed), run_dir,
                  progress=False)
    summary = json.loads((run_dir / "summary.json").read_text())
    return {"scenario": scenario, "method": "kgrl", "episodes": episodes, "env_steps": summary["env_steps"],
            "gradient_steps": summary["gradient_steps"], "step_gap_ms": summary["step_gap_ms"],
            "learn_wall_s": summary["wall_time_s"], "total_s": time.perf_counter() - t0}
