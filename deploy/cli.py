"""The ``khgrl`` command: one entry point, one subcommand per job (each with ``--help``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

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
    from khgrl.common.lerobot.demos import is_lerobot_spec, load_lerobot_demos
    from khgrl.common.tasks.demos import load_demos
    from khgrl.common.tasks.passage.scenarios import get_scenario

    demos = load_lerobot_demos(args.demos) if is_lerobot_spec(args.demos) else load_demos(args.demos)
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


def _cmd_reference(args: argparse.Namespace) -> int:
    from khgrl.common.config.settings import resolve
    from khgrl.learner.baseline import ReferenceConfig, run_reference

    config = ReferenceConfig.from_run(resolve(args=args))  # RunConfig's defaults < the flags
    run_dir = Path(args.run_dir or f"runs/reference/{config.scenario}-{config.method}-seed{config.seed}")
    episodes = run_reference(config, run_dir, progress=not args.quiet)
    ok = [e.episode for e in episodes if e.success]
    print(f"{len(ok)}/{len(episodes)} successful episodes; first success: {ok[0] if ok else 'none'}; "
          f"results in {run_dir}")
    return 0


# Commands that are whole programs with their own argument parsers (each has --help):
# name -> (module, function, one-line help)
PROCESS_COMMANDS = {
    "up": ("khgrl.deploy.run.launcher", "main", "launch router, learner, actor(s) and human-input process locally"),
    "router": ("khgrl.deploy.run.router", "main", "a Zenoh router (zenoh-python in router mode)"),
    "learner": ("khgrl.learner.main", "main", "the learner process (TQC, replay buffer from the transition stream)"),
    "actor": ("khgrl.actor.main", "main", "an actor process (environment loop, KGRL mapping, corrections)"),
    "human": ("khgrl.human_bridge.main", "main",
              "a human-input process (scripted, gui, keyboard, gamepad, spacemouse or replay)"),
    "experiment": ("khgrl.deploy.experiments.experiment", "main",
                   "methods x scenarios x seeds through the real system, resumable"),
    "report": ("khgrl.deploy.experiments.report", "main", "per-episode results of runs: figure and markdown table"),
    "stop": ("khgrl.deploy.run.stop", "main", "stop a run, or press / release its e-stop (--now, --release)"),
    "supervise": ("khgrl.deploy.run.supervise", "main",
                  "supervise a run's actors: the heartbeat without which a robot holds (processes started by hand)"),
    "view": ("khgrl.deploy.tools.view_cmd", "main", "a finished run in Rerun: an .rrd recording (--out) or the viewer"),
    "ready": ("khgrl.deploy.run.stop", "ready_main",
              "the robot is ready: the next episode may start (--confirm-reset)"),
    "keys": ("khgrl.deploy.run.keys_cmd", "main",
             "the run's signing keys, one per process (for hand-started processes)"),
    # by name: the benchmarks drive the deployment tools (benchmarks imports deploy, not the other way round)
    "bench": ("khgrl.benchmarks.cli", "main", "benchmarks that print numbers (khgrl bench --help)"),
}
# the processes a supervisor starts: they die with it, from before their (slow) imports on
SUPERVISED = ("router", "learner", "actor", "human")


def _add_demos(sub) -> None:
    from khgrl.common.tasks.passage.scenarios import SCENARIOS  # (numpy: not for khgrl stop --now's quick start)

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
    from khgrl.common.tasks.passage.scenarios import SCENARIOS

    kmp = sub.add_parser("kmp", help="LC-NS-KMP models").add_subparsers(dest="action", required=True, metavar="ACTION")
    p = kmp.add_parser("fit", help="fit GMM/GMR + LC-NS-KMP to a demonstration file and plot it")
    p.add_argument("demos", help="demonstrations (.npz with array 'demos' (M,N,O), or .csv 'demo,step,y0,...', or a "
                                 "LeRobot dataset lerobot:PATH[?feature=NAME&dims=A:B&n=N]: one demonstration per "
                                 "episode, resampled to n points, default the longest episode's frames)")
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
    from khgrl.common.config.settings import add_config_flags

    p = sub.add_parser("reference", help="single-process SB3 TQC baseline on the passage world (no Zenoh)")
    add_config_flags(p, "reference")  # scenario, method, episodes, seed, human and TQC settings: RunConfig's
    p.add_argument("--run-dir", default=None,
                   help="output directory (default: runs/reference/SCENARIO-METHOD-seedN)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (default: off)")
    p.set_defaults(func=_cmd_reference)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="khgrl", description="KhGRL: kernelized human-guided RL (actor, learner "
                                                                "and human-input processes over Zenoh).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, _, help_text) in PROCESS_COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    _add_demos(sub)
    _add_kmp(sub)
    _add_reference(sub)
    from khgrl.deploy.tools.evaluate import add_parser as _add_eval

    _add_eval(sub)
    from khgrl.deploy.tools.export import add_parser as _add_export

    _add_export(sub)
    from khgrl.deploy.run.certs_cmd import add_parser as _add_certs
    from khgrl.deploy.run.secure import add_configs_parser

    add_configs_parser(_add_certs(sub))
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in PROCESS_COMMANDS:
        import importlib

        module, func, _ = PROCESS_COMMANDS[argv[0]]
        if argv[0] in SUPERVISED:
            from khgrl.common.process import die_with_parent  # (not for khgrl stop --now: a quick start)

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
