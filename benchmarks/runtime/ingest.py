"""Measurement 1: transitions per second a learner ingests (it never trains): without durability, with its journal
(timed until the last batch is acked durable), and with the old full checkpoints every 2000 transitions."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from khgrl.benchmarks.runtime.link import Link, batches
from khgrl.benchmarks.runtime.procs import BENCH_ACTOR, BenchProcs, run_id, wait_until
from khgrl.common.delivery.transport import open_client

__all__ = ["measure_ingest"]


def measure_ingest(procs: BenchProcs, ep: str, work: Path, *, n: int, batch: int, inflight: int,
                   checkpoint_every: int, seed: int, report: Callable[[int, int], None], journal: bool = False,
                   buffer_size: int | None = None, signed: bool = False) -> dict:
    """Publish ``n`` transitions to a fresh learner and time them from the first put to the last ack (with the
    journal: also to the ack saying the last batch durable, ``durable_s``).

    :param procs: the benchmark's processes
    :param ep: the router endpoint
    :param work: the work directory
    :param n: transitions
    :param batch: transitions per batch
    :param inflight: batches beyond the last acknowledged at most
    :param checkpoint_every: the learner's full-checkpoint interval (0: none, or the journal's schedule)
    :param seed: seed of the transitions
    :param report: ``report(done, n)`` as the acks come in
    :param journal: the learner journals (``--journal``; else ``--no-journal``)
    :param buffer_size: the learner's replay buffer (None: its default); with the journal a full checkpoint
        comes each time the journal holds this many transitions
    :param signed: the run has its key and role keys (as ``khgrl up`` makes them): every batch carries the run key's
        ``mac`` and the actor's Ed25519 signature, and the learner checks both
    """
    tag = f"ingest-{'journal' if journal else 'ckpt'}{checkpoint_every}{'-signed' if signed else ''}"
    run = run_id(tag)
    payloads = batches(n, batch, seed, _signer(work / tag) if signed else None)
    extra = ["--buffer-size", str(buffer_size)] if buffer_size else []
    # the learner is told the batch size this process publishes: its lead cap (max_lead + 2 batches) then holds a
    # batch (with the default 8 it was 24 transitions and every 256-transition batch was refused as over_lead)
    learner = procs.learner(f"learner-{tag}", run, ep, work / tag, "--learning-starts", str(10**9),
                            "--checkpoint-every", str(checkpoint_every), "--journal" if journal else "--no-journal",
                            "--batch", str(batch), *extra)
    try:
        with open_client(ep) as session:
            link = Link(session, run)
            try:
                link.wait_learner(learner)
                res = link.stream(payloads, inflight, on_progress=lambda k: report(k * batch, n), durable=journal)
                # the learner's own count (status about every second)
                seen = wait_until(lambda: [m for m in link.statuses() if m.info.ingested >= n], 5.0,
                                  "learner status", [learner])
                info = seen[-1].info
            finally:
                link.close()
    finally:
        learner.stop(30.0)
    durable_s = res["durable_s"]
    return {"transitions": n, "batch": batch, "inflight": inflight, "checkpoint_every": checkpoint_every,
            "journal": journal, "buffer_size": buffer_size, "elapsed_s": res["elapsed_s"],
            "transitions_per_s": n / res["elapsed_s"], "durable_s": durable_s,
            "durable_transitions_per_s": n / durable_s if durable_s else None, "resends": res["resends"],
            "learner_ingested": info.ingested, "learner_duplicates": info.duplicates.get(BENCH_ACTOR, 0),
            "learner_checkpoints": info.checkpoints, "learner_iterations": info.iterations}


def _signer(run_dir: Path):
    """The run key and role keys of a run in ``run_dir`` (learner ``learner``, :data:`BENCH_ACTOR`); returns what the
    actor signs with."""
    from khgrl.common.delivery import run_key
    from khgrl.common.delivery.data_keys import DataKeys
    from khgrl.common.delivery.role_keys import make_run_keys

    run_key.create(run_dir, fresh=True)
    make_run_keys(run_dir, [("learner", "learner"), ("actor", BENCH_ACTOR)], fresh=True)
    return DataKeys.of_run(run_dir, "actor", BENCH_ACTOR)
