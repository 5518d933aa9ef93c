"""``khgrl bench BENCHMARK``: the benchmarks, declared once in :data:`BENCHMARKS` (module, function, help, flags).

Each benchmark is a function ``run_*_benchmark(**flags)`` whose keyword arguments are its flags' names; this module
builds the parser from the table and calls the function (lists become tuples). ``khgrl`` (:mod:`khgrl.deploy.cli`)
starts it by module name, like its process commands: the benchmarks use the deployment tools (the supervisor,
``khgrl up``'s task check, the secure set-up), so ``benchmarks`` imports ``deploy`` and not the other way round.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from typing import Any

from khgrl.common.tasks.passage.scenarios import SCENARIOS

__all__ = ["Benchmark", "BENCHMARKS", "build_parser", "main"]


def _flag(*names: str, **kw: Any) -> tuple[tuple[str, ...], dict[str, Any]]:
    """One flag: ``add_argument``'s names and keywords."""
    return names, kw


def _at_least_one(text: str) -> int:
    """An argparse type: an integer >= 1 (``--senders 0`` is a usage error, not a division by zero)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{n} is not >= 1")
    return n


SEED = _flag("--seed", type=int, default=0, help="seed (default: %(default)s)")
OUT = _flag("--out", default=None, help="also write the results as JSON here (default: none)")
RATE = _flag("--rate", type=float, default=50.0, help="the actors' control rate in Hz (default: %(default)s)")


@dataclass(frozen=True)
class Benchmark:
    """One ``khgrl bench`` command: ``module.function(**flags)``."""

    module: str
    function: str
    help: str
    flags: tuple[tuple[tuple[str, ...], dict[str, Any]], ...]


BENCHMARKS: dict[str, Benchmark] = {
    "fetch-scenes": Benchmark("khgrl.benchmarks.fetch_scenes", "run_fetch_scenes_benchmark",
                              "scripted rollouts over seeded scenes of fetch:random / fetch:obstacle: the teacher "
                              "re-targeted, the demonstrations' and the adapted KMP mean, without and with the "
                              "scripted human (no learning)", (
        _flag("--scenes", type=int, default=20, help="scenes per task (default: %(default)s)"),
        _flag("--seed", type=int, default=3, help="run seed of the scenes (default: %(default)s)"),
        _flag("--tasks", nargs="+", default=["fetch:random", "fetch:obstacle"],
              help="task specs (default: %(default)s)"),
        OUT)),
    "kmp": Benchmark("khgrl.benchmarks.kmp", "run_kmp_benchmark",
                     "per-step LC-NS-KMP cost: tables vs direct formula vs lc-ns-kmp (N=400, O=2, F=4)", (
        _flag("--repeats", type=int, default=2000, help="timed calls per case (median reported; default: %(default)s)"),
        SEED, OUT)),
    "runtime": Benchmark("khgrl.benchmarks.runtime", "run_runtime_benchmark",
                         "distributed runtime: ingest rate, weights latency, actor loop period vs single-process SB3, "
                         "learner gradient steps/s vs standalone TQC", (
        _flag("--quick", action="store_true", help="small sizes for a smoke run (< 3 min; default: off)"),
        _flag("--episodes", type=int, default=None, help="single-process reference episodes (default: 2; quick 1)"),
        _flag("--actor-episodes", type=int, default=None, help="episodes of the 50 Hz actor (default: 10; quick 2)"),
        _flag("--ingest-transitions", type=int, default=None,
              help="transitions published for the ingest rate, without durability and with the learner's journal "
                   "(default: 200000; quick 50000)"),
        _flag("--ingest-checkpoint-transitions", type=int, default=None,
              help="the same without the journal, with full checkpoints every 2000 (default: 100000; quick 20000)"),
        _flag("--batch", type=int, default=256, help="transitions per published batch (default: %(default)s)"),
        _flag("--inflight", type=int, default=8, help="unacknowledged batches at most (default: %(default)s)"),
        _flag("--train-seconds", type=float, default=None,
              help="learner and standalone train() time, each, in alternating slices (default: 30 s in 3 rounds; "
                   "quick 10 s in 2)"),
        RATE,
        _flag("--scenario", default="high_cov", choices=tuple(SCENARIOS), help="scenario (default: %(default)s)"),
        _flag("--loss-check", action=argparse.BooleanOptionalAction, default=None,
              help="learner SIGKILL + resume, count lost/duplicated transitions (default: on, off with --quick)"),
        SEED,
        _flag("--rt-priority", type=int, default=20,
              help="also measure the 50 Hz actor with its control loop under SCHED_FIFO at this priority (needs "
                   "root; 0: skip; default: %(default)s)"),
        _flag("--keep", action="store_true", help="keep the work directory (logs, run dirs; default: off)"),
        OUT)),
    "learner": Benchmark("khgrl.benchmarks.learner_step", "run_learner_benchmark",
                         "gradient steps/s of the learner's TQC next to a raw-torch TQC step of the same networks, "
                         "the learner's SAC, HIL-SERL's SAC (sac_ln) with uniform and RLPD sampling, and a raw SAC "
                         "step with 1 and 10 LayerNorm critics (batched), per device "
                         "(cpu, cuda)", (
        _flag("--devices", nargs="+", default=["cpu"], choices=["cpu", "cuda"],
              help="devices to measure (default: cpu; cuda where torch sees a GPU)"),
        _flag("--seconds", type=float, default=20.0, help="time per side and device (default: %(default)s)"),
        _flag("--threads", type=int, default=1, help="torch threads (default: %(default)s, the learner's)"),
        _flag("--ensembles", type=int, nargs="+", default=[1, 10],
              help="critic ensemble sizes of the raw-torch SAC step (default: 1 10)"),
        SEED, OUT)),
    "scale": Benchmark("khgrl.benchmarks.scale", "run_scale_benchmark",
                       "N actors into one learner through khgrl up: ingest/s, learner memory, inbox depth, weights "
                       "latency, loop period, exactly once after Ctrl-C", (
        _flag("--actors", type=int, nargs="+", default=[1, 2, 4, 8], help="actor counts (default: 1 2 4 8)"),
        _flag("--rates", type=float, nargs="+", default=[0.0, 50.0],
              help="actor rates in Hz, 0 = as fast as possible (default: 0 50)"),
        _flag("--modes", nargs="+", default=["simulation", "robot"], choices=["simulation", "robot"],
              help="flow-control modes (default: simulation robot)"),
        _flag("--seconds", type=float, default=60.0, help="length of each case (default: %(default)s)"),
        SEED,
        _flag("--work", default="runs/bench-scale", help="run directories (default: %(default)s)"),
        _flag("--device", default="auto", choices=["auto", "cpu", "cuda"],
              help="the learner's --device (default: %(default)s)"),
        OUT)),
    "images": Benchmark("khgrl.benchmarks.images", "run_images_benchmark",
                        "N actors with two 128x128 cameras into one learner through khgrl up (robot mode, no "
                        "training), frames as copies and on Zenoh's shared memory, against the same world as a "
                        "state vector: ingest/s, actor loop p99, CPU per transition by process, learner RSS, "
                        "resident bytes per transition, exactly once", (
        _flag("--actors", type=_at_least_one, default=8, help="actors of each case (default: %(default)s)"),
        _flag("--rate", type=float, default=20.0, help="their rate in Hz (default: %(default)s)"),
        _flag("--seconds", type=float, default=60.0, help="length of each case (default: %(default)s)"),
        SEED,
        _flag("--work", default="runs/bench-images", help="run directories (default: %(default)s)"),
        OUT)),
    "ingest": Benchmark("khgrl.benchmarks.ingest_many", "run_ingest_benchmark",
                        "S sender processes into one learner: transitions/s acknowledged", (
        _flag("--senders", type=_at_least_one, default=8, help="sender processes (default: %(default)s)"),
        _flag("--transitions", type=int, default=400_000, help="transitions in all (default: %(default)s)"),
        _flag("--batch", type=int, default=256, help="transitions per batch (default: %(default)s)"),
        _flag("--window", type=int, default=16, help="unacknowledged batches per sender (default: %(default)s)"),
        SEED, OUT)),
    "secure": Benchmark("khgrl.benchmarks.secure", "run_secure_benchmark",
                        "mutual TLS + access control vs plain TCP: ingest/s and weights latency", (
        _flag("--senders", type=_at_least_one, default=8,
              help="senders of the ingest measurement (default: %(default)s)"),
        _flag("--transitions", type=int, default=200_000, help="transitions per ingest (default: %(default)s)"),
        _flag("--actors", type=int, default=2, help="actors of the khgrl up measurement (default: %(default)s)"),
        RATE,
        _flag("--seconds", type=float, default=60.0, help="length of each khgrl up (default: %(default)s)"),
        _flag("--repeats", type=int, default=2, help="pairs of each measurement (default: %(default)s)"),
        SEED, OUT)),
    "flood": Benchmark("khgrl.benchmarks.flood", "run_flood_benchmark",
                       "the actor's control-loop period before, during and after a message flood", (
        _flag("--messages", type=int, default=100_000, help="garbage messages (default: %(default)s)"),
        RATE,
        _flag("--quiet-s", type=float, default=15.0, help="seconds before and after (default: %(default)s)"),
        _flag("--rt-priority", type=int, default=0,
              help="actor loop under SCHED_FIFO at this priority, 0: normal scheduling (default: %(default)s)"),
        SEED, OUT)),
    "robot": Benchmark("khgrl.benchmarks.robot_run", "run_robot_benchmark",
                       "a robot-style run in real time: gym-hil's Panda at 10 Hz in robot mode with the safety layer, "
                       "confirmed resets, an e-stop, physical pushes, a learner SIGKILL + resume, the link lost and "
                       "the actor restarted under the e-stop", (
        _flag("--rate", type=float, default=10.0, help="the control rate in Hz (default: %(default)s)"),
        _flag("--episodes", type=int, default=4, help="episodes, at least 4; one more after the restart under the "
                                                       "e-stop (default: %(default)s)"),
        _flag("--down", type=float, default=3.0, help="seconds the learner stays dead (default: %(default)s)"),
        _flag("--seed", type=int, default=1, help="seed (default: %(default)s)"),
        _flag("--work", default="runs/bench-robot", help="run directories (default: %(default)s)"),
        OUT)),
    "view": Benchmark("khgrl.benchmarks.view_bench", "run_view_benchmark",
                      "the actor's control-loop period without a view and with khgrl up --view rerun:FILE.rrd "
                      "(the passage world, the same seeded run, alternating)", (
        _flag("--episodes", type=int, default=6, help="episodes per run (default: %(default)s)"),
        RATE,
        _flag("--repeats", type=int, default=2, help="pairs of runs (default: %(default)s)"),
        SEED,
        _flag("--work", default="runs/bench-view", help="run directories (default: %(default)s)"),
        OUT)),
    "control": Benchmark("khgrl.benchmarks.control_sign", "run_control_benchmark",
                         "signed control: the actor's decode + verification per message, the sender's signature, and "
                         "what khgrl stop's path pays once (import, key load)", (
        _flag("--messages", type=int, default=2000, help="messages per case (default: %(default)s)"),
        OUT)),
    "vouch": Benchmark("khgrl.benchmarks.vouch", "run_vouch_benchmark",
                       "human data vouched for: a client's signature per correction, the actor's evidence per row, the "
                       "learner's check per intervened row (issue 34, point 6)", (
        _flag("--rows", type=int, default=256, help="intervened rows per batch (default: %(default)s)"),
        _flag("--repeats", type=int, default=20, help="timed batches per case (default: %(default)s)"),
        OUT)),
    "queries": Benchmark("khgrl.benchmarks.queries", "run_queries_benchmark",
                         "the learner's gradient steps/s while a monitor floods the weights queryable", (
        _flag("--qps", type=float, default=1000.0, help="queries per second of the flood (default: %(default)s)"),
        _flag("--seconds", type=float, default=15.0,
              help="length of each quiet and each flooded window (default: %(default)s)"),
        _flag("--rounds", type=int, default=2, help="quiet/flooded window pairs (default: %(default)s)"),
        SEED,
        _flag("--work", default="runs/bench-queries", help="run directories (default: %(default)s)"),
        OUT)),
}


def build_parser() -> argparse.ArgumentParser:
    """``khgrl bench`` with one sub-command per entry of :data:`BENCHMARKS`."""
    parser = argparse.ArgumentParser(prog="khgrl bench", description="Benchmarks that print numbers.")
    sub = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    for name, bench in BENCHMARKS.items():
        p = sub.add_parser(name, help=bench.help, description=bench.help)
        for names, kw in bench.flags:
            p.add_argument(*names, **kw)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one benchmark; 2 with a one-line error if its settings are bad.

    :param argv: command-line arguments after ``bench`` (default: ``sys.argv[1:]``)
    """
    args = vars(build_parser().parse_args(argv))
    bench = BENCHMARKS[args.pop("benchmark")]
    run = getattr(importlib.import_module(bench.module), bench.function)
    try:
        run(**{k: tuple(v) if isinstance(v, list) else v for k, v in args.items()})
    except (ValueError, FileNotFoundError) as exc:
        print(f"khgrl bench: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
