"""``khgrl bench runtime``: the measurements one after the other on one router, with a progress display, then
the table and the JSON record."""

from __future__ import annotations

import json
import os
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from khgrl.benchmarks.runtime.actor import measure_actor, measure_reference
from khgrl.benchmarks.runtime.ingest import measure_ingest
from khgrl.benchmarks.runtime.procs import BenchProcs, load
from khgrl.benchmarks.runtime.resume import measure_kill_resume
from khgrl.benchmarks.runtime.table import load_note, results_table
from khgrl.benchmarks.runtime.train import measure_train

__all__ = ["run_runtime_benchmark", "Sizes"]


def _pick(value, quick: bool, small, default):
    return value if value is not None else (small if quick else default)


@dataclass(frozen=True)
class Sizes:
    """The benchmark's settings (recorded as ``config`` in the JSON)."""

    quick: bool
    episodes: int
    actor_episodes: int
    ingest_transitions: int
    ingest_checkpoint_transitions: int
    batch: int
    inflight: int
    train_seconds: float
    train_rounds: int
    rate_hz: float
    scenario: str
    loss_check: bool
    seed: int
    rt_priority: int

    def validate(self) -> "Sizes":
        if not 1 <= self.batch <= 4096 or min(self.inflight, self.episodes, self.actor_episodes) < 1 \
                or self.rate_hz <= 0:
            raise ValueError("--batch in [1, 4096], --inflight, --episodes, --actor-episodes and --rate must be "
                             "positive")
        return self


class _Stages:
    """Runs the measurements in order, each as a task of the progress display."""

    def __init__(self, sizes: Sizes, procs: BenchProcs, work: Path, progress, record: dict) -> None:
        self.s, self.procs, self.work, self.progress, self.record = sizes, procs, work, progress, record
        self.results = record["results"]
        names = (["ingest", "ingest_signed", "ingest_journal", "ingest_ckpt", "train", "actor"]
                 + (["actor_rt"] if sizes.rt_priority else []) + ["reference"]
                 + (["kill_resume"] if sizes.loss_check else []))
        self.overall = progress.add_task("[bold]overall", total=len(names), info="")

    def _task(self, name: str, description: str, total: float = 1.0):
        self.record["load"][name] = load()
        return self.progress.add_task(description, total=total, info="")

    def _done(self, task, info: str, completed: float | None = None) -> None:
        self.progress.update(task, info=info, **({} if completed is None else {"completed": completed}))
        self.progress.advance(self.overall)

    def run(self) -> None:
        task = self._task("router", "router", 1)
        ep = self.procs.router()
        self.progress.update(task, completed=1, info=ep)
        self.ingest(ep)
        self.train(ep)
        self.actor(ep, 0)
        if self.s.rt_priority:
            self.actor(ep, self.s.rt_priority)
        self.reference()
        if self.s.loss_check:
            self.kill_resume(ep)

    def ingest(self, ep: str) -> None:
        s = self.s
        n = s.ingest_transitions
        stages = (("ingest", n, 0, False, None, "no durability"),
                  ("ingest_signed", n, 0, False, None, "no durability, signed per role"),
                  # the journal's schedule: a full checkpoint each time it holds a replay buffer's worth; a buffer of
                  # n/2 puts two in this run, one mid-way (per transition as many buffer bytes as the default 200k
                  # buffer's, and more model saves)
                  ("ingest_journal", n, 0, True, max(1000, n // 2), "journal, timed to the last durable ack"),
                  ("ingest_ckpt", s.ingest_checkpoint_transitions, 2000, False, None,
                   "no journal, full checkpoint every 2000"))
        for key, count, every, journal, buffer, what in stages:
            signed = key == "ingest_signed"
            task = self._task(key, f"1. ingest {count} transitions ({what})", count)
            res = measure_ingest(self.procs, ep, self.work, n=count, batch=s.batch, inflight=s.inflight,
                                 checkpoint_every=every, seed=s.seed, journal=journal, buffer_size=buffer,
                                 signed=signed,
                                 report=lambda k, n_, t=task: self.progress.update(t, completed=k, info=f"{k}/{n_}"))
            self.results[key] = res
            rate = res["durable_transitions_per_s"] or res["transitions_per_s"]
            self._done(task, f"{rate:,.0f} transitions/s", count)

    def train(self, ep: str) -> None:
        s = self.s
        task = self._task("train", f"4. learner vs standalone train() ({s.train_seconds:.0f} s each, "
                                   f"{s.train_rounds} rounds)")
        res = measure_train(self.procs, ep, self.work, seconds=s.train_seconds, rounds=s.train_rounds, batch=s.batch,
                            inflight=s.inflight, seed=s.seed,
                            report=lambda what, frac: self.progress.update(task, completed=frac, info=what))
        self.results["train"] = res
        self._done(task, f"{res['learner_grad_steps_per_s']:.1f} vs {res['standalone_grad_steps_per_s']:.1f} "
                         f"gradient steps/s", 1.0)

    def actor(self, ep: str, rt_priority: int) -> None:
        s = self.s
        key = "actor_rt" if rt_priority else "actor"
        what = f"3b. actor at {s.rate_hz:g} Hz under SCHED_FIFO {rt_priority}" if rt_priority else \
            f"2+3. actor at {s.rate_hz:g} Hz, {s.actor_episodes} episode(s)"
        task = self._task(key, f"{what}, learner training", s.actor_episodes)
        res = measure_actor(self.procs, ep, self.work, scenario=s.scenario, episodes=s.actor_episodes,
                            rate=s.rate_hz, seed=s.seed, rt_priority=rt_priority,
                            report=lambda k, n_: self.progress.update(task, completed=k, info=f"episode {k}/{n_}"))
        self.results[key] = res
        refused = "" if res["realtime"] or not rt_priority else " (SCHED_FIFO refused: normal scheduling)"
        lp = res["loop_period_ms"] or {}
        period = f"{lp['p50']:.1f} / {lp['p99']:.1f} ms" if lp.get("p50") is not None else "-"
        self._done(task, f"period p50/p99 {period}{refused}", s.actor_episodes)

    def reference(self) -> None:
        s = self.s
        task = self._task("reference", f"3. single-process SB3 reference, {s.episodes} episode(s)")
        res = measure_reference(self.work, scenario=s.scenario, episodes=s.episodes, seed=s.seed)
        self.results["reference"] = res
        self._done(task, f"{res['env_steps']} env steps", 1)

    def kill_resume(self, ep: str) -> None:
        task = self._task("kill_resume", "5. learner SIGKILL + --resume, exactly-once check")
        res = measure_kill_resume(self.procs, ep, self.work, seed=self.s.seed,
                                  report=lambda what: self.progress.update(task, info=what))
        self.results["kill_resume"] = res
        self._done(task, f"lost {res['lost']}, duplicated {res['duplicated']}", 1)


def run_runtime_benchmark(*, quick: bool = False, out: str | None = None, episodes: int | None = None,
                          actor_episodes: int | None = None, ingest_transitions: int | None = None,
                          ingest_checkpoint_transitions: int | None = None, batch: int = 256, inflight: int = 8,
                          train_seconds: float | None = None, rate: float = 50.0, scenario: str = "high_cov",
                          loss_check: bool | None = None, seed: int = 0, keep: bool = False,
                          rt_priority: int = 20) -> dict:
    """Run the measurements (:mod:`khgrl.benchmarks.runtime`), print a table, write JSON to ``out``; returns the record.

    :param quick: small sizes (a smoke run); each size below given as None takes the default or quick value
    :param out: also write the record as JSON here
    :param keep: keep the work directory (logs, run directories)
    :param rt_priority: SCHED_FIFO priority for measurement 3b (0: skip it)
    """
    from rich.console import Console
    from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    sizes = Sizes(quick=quick, episodes=_pick(episodes, quick, 1, 2),
                  actor_episodes=_pick(actor_episodes, quick, 2, 10),
                  ingest_transitions=_pick(ingest_transitions, quick, 50_000, 200_000),
                  ingest_checkpoint_transitions=_pick(ingest_checkpoint_transitions, quick, 20_000, 100_000),
                  batch=batch, inflight=inflight, train_seconds=_pick(train_seconds, quick, 10.0, 30.0),
                  train_rounds=2 if quick else 3, rate_hz=rate, scenario=scenario,
                  loss_check=_pick(loss_check, quick, False, True), seed=seed, rt_priority=rt_priority).validate()
    console = Console(width=None if sys.stdout.isatty() else 150)
    work = Path(tempfile.mkdtemp(prefix="khgrl-bench-runtime-"))
    machine = {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
               "load_start": load()}
    console.print(f"[bold]KhGRL runtime benchmark[/] ({'quick' if quick else 'default'} sizes; {os.cpu_count()} "
                  f"CPUs, load average {machine['load_start']}); work dir {work}")
    record: dict[str, Any] = {"config": asdict(sizes), "machine": machine, "results": {}, "load": {}}
    procs = BenchProcs(work)
    t_start = time.perf_counter()
    ok = False
    progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                        TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console, transient=False)
    try:
        with progress:
            _Stages(sizes, procs, work, progress, record).run()
        ok = True
    finally:
        procs.close()
        if ok and not keep:
            shutil.rmtree(work, ignore_errors=True)
        elif not ok:
            console.print(f"[red]benchmark failed[/]: logs kept in {work / 'logs'}")
    machine["load_end"] = load()
    record["wall_s"] = time.perf_counter() - t_start
    record["work_dir"] = str(work) if keep else None
    console.print(results_table(record))
    record["note"] = load_note(record)
    console.print(record["note"])
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(record, indent=2))
        console.print(f"wrote {out}")
    return record
