"""The ``khgrl`` command: one entry point, one subcommand per job (each with ``--help``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from khgrl.common.config.settings import METHODS, SCENARIOS
from khgrl.common.process import die_with_parent

__all__ = ["main", "build_parser"]


def _cmd_demos_make(args: argparse.Namespace) -> int:
    from khgrl.common.tasks.demos import save_demos
    from khgrl.common.tasks.passage.scenarios import make_demos

    demos = make_demos(args.scenario, n_demos=args.n_demos, n_steps=args.n_steps, seed=args.seed)
    path = save_demos(args.out, demos)
    print(f"wrote {demos.shape[0]} demonstrations x {demos.shape[1]} steps x {demos.shape[2]} outputs to {path}")
    return 0


def _cmd_kmp_fit(args: argparse.Namespace) -> int:
    from khgrl.common.kmp.fit import KMPConfig, box_constraints, fit_model
    from khgrl.common.kmp.plots import plot_kmp
    from khgrl.common.tasks.demos import load_demos
    from khgrl.common.tasks.passage.scenarios import get_scenario

    demos = load_demos(args.demos)
    config = KMPConfig(
        lam=args.lam, beta=args.beta, length_scale=args.length_scale, n_components=args.components, seed=args.seed
    )
    o = demos.shape[2]
    constraints = None
    if args.box is not None:
        lo, hi = args.box
        constraints = box_constraints([lo] * o, [hi] * o)
    model, ref = fit_model(demos, config, constraints)
    out = Path(args.out)
    scenario = get_scenario(args.scenario) if args.scenario else None
    plot_kmp(model, ref, demos, out, title=f"{Path(args.demos).name}: LC-NS-KMP (O = {o})", scenario=scenario,
             workspace=None if args.box is None else ([args.box[0]] * o, [args.box[1]] * o))
    import numpy as np

    proj = np.linalg.eigvalsh(model.grid_projector)[:, -1]
    summary = {
        "demos": str(args.demos),
        "shape": list(demos.shape),
        "config": config.to_dict(),
        "box": args.box,
        "projector_max": float(proj.max()),
        "projector_min": float(proj.min()),
        "mean_minus_gmr_max_abs": float(np.abs(model.grid_mean - ref.mu).max()),
    }
    out.with_suffix(".json").write_text(json.dumps(summary, indent=2))
    print(f"fitted LC-NS-KMP on {demos.shape[0]} demos x {demos.shape[1]} points; projector norm in "
          f"[{summary['projector_min']:.2e}, {summary['projector_max']:.2e}]")
    print(f"wrote {out} and {out.with_suffix('.json')}")
    return 0


def _cmd_bench_kmp(args: argparse.Namespace) -> int:
    from khgrl.benchmarks.kmp import run_kmp_benchmark

    run_kmp_benchmark(repeats=args.repeats, seed=args.seed, out=args.out)
    return 0


def _cmd_bench_runtime(args: argparse.Namespace) -> int:
    from khgrl.benchmarks.runtime import run_runtime_benchmark

    run_runtime_benchmark(quick=args.quick, out=args.out, episodes=args.episodes, actor_episodes=args.actor_episodes,
                          ingest_transitions=args.ingest_transitions,
                          ingest_checkpoint_transitions=args.ingest_checkpoint_transitions, batch=args.batch,
                          inflight=args.inflight, train_seconds=args.train_seconds, rate=args.rate,
                          scenario=args.scenario, loss_check=args.loss_check, seed=args.seed, keep=args.keep,
                          rt_priority=args.rt_priority)
    return 0


def _cmd_reference(args: argparse.Namespace) -> int:
    from khgrl.learner.baseline import ReferenceConfig, run_reference

    config = ReferenceConfig(scenario=args.scenario, method=args.method, episodes=args.episodes, seed=args.seed,
                             human_noise=args.human_noise)
    run_dir = Path(args.run_dir or f"runs/reference/{args.scenario}-{args.method}-seed{args.seed}")
    episodes = run_reference(config, run_dir, progress=not args.quiet)
    ok = [e.episode for e in episodes if e.success]
    print(f"{len(ok)}/{len(episodes)} successful episodes; first success: {ok[0] if ok else 'none'}; "
          f"results in {run_dir}")
    return 0


# Commands that are whole programs with their own argument parsers (each has --help):
# name -> (module, function, one-line help)
PROCESS_COMMANDS = {
    "up": ("khgrl.deploy.launcher", "main", "launch router, learner, actor(s) and human-input process locally"),
    "router": ("khgrl.deploy.router", "main", "a Zenoh router (zenoh-python in router mode)"),
    "learner": ("khgrl.learner.main", "main", "the learner process (TQC, replay buffer from the transition stream)"),
    "actor": ("khgrl.actor.main", "main", "an actor process (environment loop, KGRL mapping, corrections)"),
    "human": ("khgrl.human_bridge.main", "main", "a human-input process (scripted, gui, keyboard, gamepad or replay)"),
    "experiment": ("khgrl.deploy.experiment", "main", "methods x scenarios x seeds through the real system, resumable"),
    "report": ("khgrl.deploy.report", "main", "per-episode results of runs: figure and markdown table"),
}
# the processes a supervisor starts: they die with it, from before their (slow) imports on
SUPERVISED = ("router", "learner", "actor", "human")


def _add_demos(sub) -> None:
    demos = sub.add_parser("demos", help="demonstration files").add_subparsers(dest="action", required=True,
                                                                                metavar="ACTION")
    p = demos.add_parser("make", help="generate the seeded demonstrations of a passage-world scenario")
    p.add_argument("--scenario", default="high_cov", choices=SCENARIOS, help="scenario (default: %(default)s)")
    p.add_argument("--out", required=True, help="output file (.npz or .csv; required)")
    p.add_argument("--n-demos", type=int, default=9, help="demonstrations (default: %(default)s)")
    p.add_argument("--n-steps", type=int, default=400, help="points per demonstration (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.set_defaults(func=_cmd_demos_make)
    from khgrl.human_bridge.record import add_parser as _add_record

    _add_record(demos)


def _add_kmp(sub) -> None:
    kmp = sub.add_parser("kmp", help="LC-NS-KMP models").add_subparsers(dest="action", required=True, metavar="ACTION")
    p = kmp.add_parser("fit", help="fit GMM/GMR + LC-NS-KMP to a demonstration file and plot it")
    p.add_argument("demos", help="demonstrations (.npz with array 'demos' (M,N,O), or .csv 'demo,step,y0,...')")
    p.add_argument("--out", default="runs/kmp.png",
                   help="PNG to write (a .json summary is written beside it; default: %(default)s)")
    p.add_argument("--lam", type=float, default=1.0, help="KMP regulariser lambda (default: %(default)s)")
    p.add_argument("--beta", type=float, default=10.0,
                   help="null-space weight beta (gamma = lambda + beta; default: %(default)s)")
    p.add_argument("--length-scale", type=float, default=0.02,
                   help="RBF length scale in normalised time (default: %(default)s)")
    p.add_argument("--components", type=int, default=10, help="GMM components (default: %(default)s)")
    p.add_argument("--box", type=float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                   help="hard box constraints on every output (default: none)")
    p.add_argument("--scenario", choices=SCENARIOS, default=None,
                   help="draw this passage world's walls and obstacle (default: none)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.set_defaults(func=_cmd_kmp_fit)


def _add_reference(sub) -> None:
    p = sub.add_parser("reference", help="single-process SB3 TQC baseline on the passage world (no Zenoh)")
    p.add_argument("--scenario", default="high_cov", choices=SCENARIOS, help="scenario (default: %(default)s)")
    p.add_argument("--method", default="khgrl", choices=METHODS,
                   help="khgrl: scripted human at the paper's episodes (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=60, help="episodes (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--human-noise", type=float, default=0.0,
                   help="std of the scripted human's hand noise (default: %(default)s)")
    p.add_argument("--run-dir", default=None,
                   help="output directory (default: runs/reference/SCENARIO-METHOD-seedN)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (default: off)")
    p.set_defaults(func=_cmd_reference)


def _cmd_bench_learner(args: argparse.Namespace) -> int:
    from khgrl.benchmarks.learner_step import run_learner_benchmark

    run_learner_benchmark(devices=tuple(args.devices), seconds=args.seconds, threads=args.threads, seed=args.seed,
                          out=args.out)
    return 0


def _cmd_bench_scale(args: argparse.Namespace) -> int:
    from khgrl.benchmarks.scale import run_scale_benchmark

    run_scale_benchmark(actors=tuple(args.actors), rates=tuple(args.rates), modes=tuple(args.modes),
                        seconds=args.seconds, seed=args.seed, work=args.work, out=args.out)
    return 0


def _cmd_bench_ingest(args: argparse.Namespace) -> int:
    from khgrl.benchmarks.ingest_many import run_ingest_benchmark

    run_ingest_benchmark(senders=args.senders, transitions=args.transitions, batch=args.batch, window=args.window,
                         seed=args.seed, out=args.out)
    return 0


def _cmd_bench_flood(args: argparse.Namespace) -> int:
    from khgrl.benchmarks.flood import run_flood_benchmark

    run_flood_benchmark(messages=args.messages, rate=args.rate, quiet_s=args.quiet_s, seed=args.seed,
                        rt_priority=args.rt_priority, out=args.out)
    return 0


def _cmd_bench_secure(args: argparse.Namespace) -> int:
    from khgrl.benchmarks.secure import run_secure_benchmark

    run_secure_benchmark(senders=args.senders, transitions=args.transitions, actors=args.actors, rate=args.rate,
                         seconds=args.seconds, repeats=args.repeats, seed=args.seed, out=args.out)
    return 0


def _add_bench(sub) -> None:
    bench = sub.add_parser("bench", help="benchmarks that print numbers").add_subparsers(dest="action", required=True,
                                                                                         metavar="ACTION")
    p = bench.add_parser("kmp", help="per-step LC-NS-KMP cost: tables vs direct formula vs lc-ns-kmp (N=400, O=2, F=4)")
    p.add_argument("--repeats", type=int, default=2000,
                   help="timed calls per case (median reported; default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    p.set_defaults(func=_cmd_bench_kmp)
    p = bench.add_parser("runtime", help="distributed runtime: ingest rate, weights latency, actor loop period vs "
                                         "single-process SB3, learner gradient steps/s vs standalone TQC")
    p.add_argument("--quick", action="store_true", help="small sizes for a smoke run (< 3 min; default: off)")
    p.add_argument("--episodes", type=int, default=None,
                   help="single-process reference episodes (default: 2; quick 1)")
    p.add_argument("--actor-episodes", type=int, default=None,
                   help="episodes of the 50 Hz actor (default: 10; quick 2)")
    p.add_argument("--ingest-transitions", type=int, default=None,
                   help="transitions published for the ingest rate (default: 200000; quick 50000)")
    p.add_argument("--ingest-checkpoint-transitions", type=int, default=None,
                   help="the same with checkpoints every 2000 (default: 100000; quick 20000)")
    p.add_argument("--batch", type=int, default=256, help="transitions per published batch (default: %(default)s)")
    p.add_argument("--inflight", type=int, default=8, help="unacknowledged batches at most (default: %(default)s)")
    p.add_argument("--train-seconds", type=float, default=None,
                   help="learner and standalone train() time, each, in alternating slices "
                        "(default: 30 s in 3 rounds; quick 10 s in 2)")
    p.add_argument("--rate", type=float, default=50.0, help="actor control rate in Hz (default: %(default)s)")
    p.add_argument("--scenario", default="high_cov", choices=SCENARIOS, help="scenario (default: %(default)s)")
    p.add_argument("--loss-check", action=argparse.BooleanOptionalAction, default=None,
                   help="learner SIGKILL + resume, count lost/duplicated transitions (default: on, off with --quick)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--rt-priority", type=int, default=20,
                   help="also measure the 50 Hz actor with its control loop under SCHED_FIFO at this priority "
                        "(needs root; 0: skip; default: %(default)s)")
    p.add_argument("--keep", action="store_true", help="keep the work directory (logs, run dirs; default: off)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    p.set_defaults(func=_cmd_bench_runtime)
    p = bench.add_parser("learner", help="gradient steps/s of the learner's TQC next to a raw-torch TQC step of the "
                                         "same networks, per device (cpu, cuda)")
    p.add_argument("--devices", nargs="+", default=["cpu"], choices=["cpu", "cuda"],
                   help="devices to measure (default: cpu; cuda where torch sees a GPU)")
    p.add_argument("--seconds", type=float, default=20.0, help="time per side and device (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s, the learner's)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    p.set_defaults(func=_cmd_bench_learner)
    p = bench.add_parser("scale", help="N actors into one learner through khgrl up: ingest/s, learner memory, inbox "
                                       "depth, weights latency, loop period, exactly once after Ctrl-C")
    p.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4, 8], help="actor counts (default: 1 2 4 8)")
    p.add_argument("--rates", type=float, nargs="+", default=[0.0, 50.0],
                   help="actor rates in Hz, 0 = as fast as possible (default: 0 50)")
    p.add_argument("--modes", nargs="+", default=["simulation", "robot"], choices=["simulation", "robot"],
                   help="flow-control modes (default: simulation robot)")
    p.add_argument("--seconds", type=float, default=60.0, help="length of each case (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--work", default="runs/bench-scale", help="run directories (default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    p.set_defaults(func=_cmd_bench_scale)
    p = bench.add_parser("ingest", help="S sender processes into one learner: transitions/s acknowledged")
    p.add_argument("--senders", type=int, default=8, help="sender processes (default: %(default)s)")
    p.add_argument("--transitions", type=int, default=400_000, help="transitions in all (default: %(default)s)")
    p.add_argument("--batch", type=int, default=256, help="transitions per batch (default: %(default)s)")
    p.add_argument("--window", type=int, default=16, help="unacknowledged batches per sender (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the result as JSON here (default: none)")
    p.set_defaults(func=_cmd_bench_ingest)
    p = bench.add_parser("secure", help="mutual TLS + access control vs plain TCP: ingest/s and weights latency")
    p.add_argument("--senders", type=int, default=8, help="senders of the ingest measurement (default: %(default)s)")
    p.add_argument("--transitions", type=int, default=200_000, help="transitions per ingest (default: %(default)s)")
    p.add_argument("--actors", type=int, default=2, help="actors of the khgrl up measurement (default: %(default)s)")
    p.add_argument("--rate", type=float, default=50.0, help="their rate in Hz (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=60.0, help="length of each khgrl up (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=2, help="pairs of each measurement (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    p.set_defaults(func=_cmd_bench_secure)
    p = bench.add_parser("flood", help="the actor's control-loop period before, during and after a message flood")
    p.add_argument("--messages", type=int, default=100_000, help="garbage messages (default: %(default)s)")
    p.add_argument("--rate", type=float, default=50.0, help="the actor's rate in Hz (default: %(default)s)")
    p.add_argument("--quiet-s", type=float, default=15.0, help="seconds before and after (default: %(default)s)")
    p.add_argument("--rt-priority", type=int, default=0,
                   help="actor loop under SCHED_FIFO at this priority, 0: normal scheduling (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    p.set_defaults(func=_cmd_bench_flood)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="khgrl", description="KhGRL: kernelized human-guided RL (actor, learner "
                                                                "and human-input processes over Zenoh).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, _, help_text) in PROCESS_COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    _add_demos(sub)
    _add_kmp(sub)
    _add_reference(sub)
    from khgrl.deploy.evaluate import add_parser as _add_eval

    _add_eval(sub)
    _add_bench(sub)
    from khgrl.deploy.certs import add_parser as _add_certs
    from khgrl.deploy.secure import add_configs_parser

    add_configs_parser(_add_certs(sub))
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in PROCESS_COMMANDS:
        import importlib

        module, func, _ = PROCESS_COMMANDS[argv[0]]
        if argv[0] in SUPERVISED:
            die_with_parent()
        return int(getattr(importlib.import_module(module), func)(argv[1:]) or 0)
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"khgrl: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
