"""Measurement 5: exactly-once across a learner kill -- an actor streams, the learner (default durability: the
journal, no full checkpoint until the end) is SIGKILLed once its journal holds 128 transitions and restarted with
``--resume``; the final checkpoint's provenance counts what was lost or duplicated."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import numpy as np
from khgrl.benchmarks.runtime.procs import BenchProcs, run_id, wait_until

__all__ = ["measure_kill_resume", "buffer_steps"]


def buffer_steps(ckpt: Path, actor: str) -> np.ndarray:
    """The actor's running indices of the transitions in a learner checkpoint's replay buffer (one per slot).

    :param ckpt: ``RUN_DIR/learner/checkpoint``
    :param actor: the actor id
    """
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    state = json.loads((ckpt / "state.json").read_text())
    arrays = load_checkpoint_arrays(ckpt)
    pos = state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]
    codes, steps = arrays["provenance_actor"][:pos], arrays["provenance_step"][:pos]
    mine = [c for c, e in enumerate(state["codes"]) if e["actor"] == actor]
    return steps[np.isin(codes, mine)]


def measure_kill_resume(procs: BenchProcs, ep: str, work: Path, *, seed: int, report: Callable[[str], None]) -> dict:
    """Kill the learner once its journal holds 128 transitions, resume it, and count the actor's transitions in
    the end.

    :param procs: the benchmark's processes
    :param ep: the router endpoint
    :param work: the work directory
    :param seed: seed of the actor
    :param report: ``report(what is happening)``
    """
    run = run_id("resume")
    run_dir = work / "resume"
    from khgrl.learner.journal_scan import read_records

    journal = run_dir / "learner" / "journal"
    largs = ["--learning-starts", "16"]
    learner = procs.learner("learner-resume-1", run, ep, run_dir, *largs)
    actor = procs.actor("actor-resume", run, ep, run_dir, "--scenario", "high_cov", "--method", "kgrl",
                        "--episodes", "2", "--seed", str(seed), "--rate", "120", "--learning-starts", "16")
    try:
        report("waiting for 128 transitions in the learner's journal")

        def journaled() -> int:
            return sum(m.n for m in read_records(journal))

        wait_until(lambda: journaled() >= 128, 180, "128 journaled transitions", [learner, actor])
        learner.kill()
        killed_at = journaled()
        time.sleep(0.5)
        report(f"learner killed with {killed_at} journaled transitions; resuming")
        learner = procs.learner("learner-resume-2", run, ep, run_dir, *largs, "--resume")
        if actor.wait(240) != 0:
            raise RuntimeError(f"actor exited with {actor.poll()}:\n{actor.tail()}")
        learner.stop(60.0)
    finally:
        learner.stop(30.0)
        actor.stop(30.0)
    summary = json.loads((run_dir / "actor-a0" / "summary.json").read_text())
    got = buffer_steps(run_dir / "learner" / "checkpoint", "a0")
    n = int(summary["transitions"])
    unique = set(got.tolist())
    return {
        "actor_transitions": n, "in_buffer": int(got.size), "killed_at_journaled": killed_at,
        "lost": len(set(range(n)) - unique), "duplicated": int(got.size - len(unique)),
        "unexpected": len(unique - set(range(n))), "actor_resends": summary["resends"],
        "actor_unconfirmed": summary["unconfirmed_transitions"],
    }
