"""``khgrl experiment``: run methods x scenarios x seeds through the real three-process system.

Every run is one ``khgrl up`` (router, learner, actor, and for KhGRL the scripted human at the paper's
episodes) in its own run directory ``OUT/<scenario>-<method>-seed<S>``; with ``system = "reference"`` it is
the single-process SB3 baseline (``khgrl reference``) instead. A configuration file (TOML or JSON) names the
grid; command-line options override it::

    khgrl experiment experiments/paper.toml --jobs 2
    khgrl experiment --scenarios high_cov --methods khgrl kgrl --seeds 0 1 2 --episodes 60 --out runs/exp
    khgrl experiment --tasks fetch:control fetch:moved --episodes 40 --out runs/fetch

``tasks`` (any ``--task`` of ``khgrl up``) replaces the passage world's ``scenarios``; a task's run directories are
named after it with ``:`` and ``.`` as ``_`` (``fetch:moved`` -> ``fetch_moved-khgrl-seed0``).

Resumable: a run whose directory holds a finished result (every process exited 0, all episodes) is not
redone; any other run directory (an interrupted or failed run) is wiped and the run starts again from
scratch, so no half-run is ever mixed into the results -- unless ``--resume-interrupted``: then a run that was
interrupted (Ctrl-C, or the machine went away while it ran) and left a learner checkpoint continues from it with
``khgrl up --resume``, and experiment.json counts its ``parts``. A run still alive is never touched.
``OUT/experiment.json`` records the resolved configuration, the machine and every run's status and wall time;
``khgrl report OUT`` analyses it. With ``--ray
ADDRESS`` the runs are Ray tasks on a cluster's workers instead (:mod:`khgrl.deploy.experiments.experiment_ray`).

The grid (configuration, plan, one run's command) is :mod:`~khgrl.deploy.experiments.grid`; here is the local
runner that walks it; the progress display is :mod:`~khgrl.deploy.experiments.experiment_progress`, Ray's runner
:mod:`~khgrl.deploy.experiments.experiment_ray`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

from khgrl.common.config.settings import REFERENCE_METHODS
from khgrl.common.tasks.passage.scenarios import SCENARIOS
from khgrl.deploy.experiments.experiment_progress import Progress, last_line
from khgrl.deploy.experiments.experiment_ray import EPISODE_LINE, RayRunner, add_ray_arguments
from khgrl.deploy.experiments.grid import (
    SYSTEMS,
    ExperimentConfig,
    RunSpec,
    load_config,
    plan_runs,
    run_argv,
    run_is_done,
    task_label,
)
from khgrl.deploy.experiments.run_results import METHOD_LABEL
from khgrl.deploy.run import rundir

__all__ = ["ExperimentConfig", "RunSpec", "task_label", "load_config", "plan_runs", "run_is_done", "run_argv", "main",
           "build_parser"]

class _Runner:
    """Runs the planned runs, ``jobs`` at a time, and keeps ``OUT/experiment.json`` current."""

    def __init__(self, cfg: ExperimentConfig, specs: list[RunSpec], progress) -> None:
        self.cfg, self.specs, self.progress = cfg, specs, progress
        self.out = Path(cfg.out)
        self.status: dict[str, dict] = _previous_status(self.out)
        self.lock = threading.Lock()
        self.stopping = False
        self.procs: dict[str, subprocess.Popen] = {}
        self.ray = RayRunner(self, lambda s: run_argv(s, cfg, self.out / s.name), lambda d: run_is_done(d, cfg))

    def record(self, name: str, **info) -> None:
        """Update one run's entry in ``experiment.json`` (merged under a file lock: several invocations on one
        directory, e.g. one per scenario, keep each other's entries)."""
        import fcntl

        with self.lock, open(self.out / ".experiment.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            self.status = {**_previous_status(self.out), name: {**self.status.get(name, {}), **info}}
            doc = {"config": asdict(self.cfg), "machine": _machine(), "updated": time.strftime("%Y-%m-%dT%H:%M:%S"),
                   "runs": self.status}
            tmp = self.out / f"experiment.json.{os.getpid()}.tmp"
            tmp.write_text(json.dumps(doc, indent=2))
            os.replace(tmp, self.out / "experiment.json")

    def one(self, spec: RunSpec) -> str:
        run_dir = self.out / spec.name
        if run_is_done(run_dir, self.cfg):  # before the Ctrl-C check: a run finished before is counted as done
            self.progress.skip(spec.name)
            self.record(spec.name, status="done", reused=True)
            return "done"
        if self.stopping:
            return "not started"
        if alive := rundir.live_run(run_dir):  # another invocation runs it: neither wiped nor resumed
            self.progress.finish(spec.name, "failed", 0.0, f"still running elsewhere: {', '.join(alive)}")
            return "failed"
        resume = self._resumable(spec.name, run_dir)
        if run_dir.exists() and not resume:
            shutil.rmtree(run_dir)  # interrupted or failed before: start again from scratch
        run_dir.mkdir(parents=True, exist_ok=True)
        argv = run_argv(spec, self.cfg, run_dir) + (["--resume"] if resume else [])
        parts = int(self.status.get(spec.name, {}).get("parts", 1)) + 1 if resume else 1
        self.record(spec.name, status="running", argv=argv, parts=parts,
                    started=time.strftime("%Y-%m-%dT%H:%M:%S"))
        t0 = time.time()
        log_path = run_dir / "experiment.log"
        with open(log_path, "a" if resume else "w") as log:
            proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True)
            with self.lock:
                self.procs[spec.name] = proc
            self.progress.start(spec.name)
            for line in proc.stdout:
                log.write(line)
                log.flush()
                m = EPISODE_LINE.search(line)
                if m:
                    self.progress.advance(spec.name, int(m.group(1) or m.group(2)))
            rc = proc.wait()
        with self.lock:
            self.procs.pop(spec.name, None)
        wall = time.time() - t0
        ok = rc == 0 and run_is_done(run_dir, self.cfg)
        status = "done" if ok else ("interrupted" if self.stopping else "failed")
        self.record(spec.name, status=status, returncode=rc, wall_time_s=round(wall, 1))
        why = "" if ok else f"{last_line(log_path.read_text(errors='replace'))} (log: {log_path})"
        self.progress.finish(spec.name, status, wall, why)
        return status

    def _resumable(self, name: str, run_dir: Path) -> bool:
        """``--resume-interrupted`` and the run was interrupted (or still marked running: its machine went away)
        with a learner checkpoint to go on from; a failed run starts again from scratch."""
        return (self.cfg.resume_interrupted and self.status.get(name, {}).get("status") in ("interrupted", "running")
                and (run_dir / "config.toml").is_file() and rundir.has_checkpoint(run_dir))

    def stop(self) -> None:
        """Ctrl-C: let each ``khgrl up`` stop its processes (SIGINT), then wait for them."""
        self.stopping = True
        with self.lock:
            procs = list(self.procs.values())
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGINT)
            except ProcessLookupError:
                pass


def _previous_status(out: Path) -> dict[str, dict]:
    """Run statuses recorded by earlier invocations on this directory (other seeds or scenarios, say)."""
    try:
        return dict(json.loads((out / "experiment.json").read_text()).get("runs", {}))
    except (OSError, ValueError, AttributeError):
        return {}


def _machine() -> dict:
    return {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform()}


def run(args: argparse.Namespace) -> int:
    overrides = {"out": args.out, "scenarios": args.scenarios, "tasks": args.tasks, "methods": args.methods,
                 "seeds": args.seeds, "episodes": args.episodes, "human_episodes": args.human_episodes,
                 "system": args.system, "jobs": args.jobs, "max_lead": args.max_lead, "timeout": args.timeout,
                 "ray": args.ray, "ray_cpus": args.ray_cpus, "ray_gpus": args.ray_gpus,
                 "until_success": args.until_success, "success_window": args.success_window,
                 "resume_interrupted": args.resume_interrupted or None,
                 "up_args": shlex.split(args.up_args) if args.up_args is not None else None}
    try:
        cfg = load_config(args.config, overrides)
    except (ValueError, OSError, TypeError) as exc:
        print(f"khgrl experiment: error: {exc}", file=sys.stderr)
        return 2
    specs = plan_runs(cfg)
    out = Path(cfg.out)
    if args.dry_run:
        for spec in specs:
            state = "done" if run_is_done(out / spec.name, cfg) else "to run"
            print(f"{spec.name:<32} {state:<7} {' '.join(run_argv(spec, cfg, out / spec.name)[2:])}")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(asdict(cfg), indent=2))
    where = f"as Ray tasks on {cfg.ray}, {cfg.ray_cpus:g} CPUs each" if cfg.ray else f"{cfg.jobs} at a time"
    print(f"khgrl experiment: {len(specs)} runs ({cfg.system}) into {out}, {where}", flush=True)
    t0 = time.time()
    progress = Progress(len(specs), cfg.episodes, enabled=not args.no_progress and sys.stdout.isatty())
    runner = _Runner(cfg, specs, progress)
    previous = signal.signal(signal.SIGINT, lambda *_: runner.stop())
    try:
        with progress, ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
            results = runner.ray.run_all(specs) if cfg.ray else list(pool.map(runner.one, specs))
    except RuntimeError as exc:  # --ray without Ray installed, or no cluster at the address
        print(f"khgrl experiment: error: {exc}", file=sys.stderr)
        return 2
    finally:
        signal.signal(signal.SIGINT, previous)
    for name, info in list(runner.status.items()):  # runs another invocation was still running when it last wrote
        if info.get("status") == "running" and run_is_done(out / name, cfg):
            runner.record(name, status="done")
    counts = {s: results.count(s) for s in sorted(set(results))}
    after = f"analyse with: khgrl report {out}" if counts.get("done") else f"no run finished: see {out}/experiment.json"
    print(f"khgrl experiment: {counts} in {time.time() - t0:.0f} s; {after}", flush=True)
    if runner.stopping:
        return 130
    return 0 if counts.get("done", 0) == len(specs) else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl experiment", description=__doc__.split("\n\n")[0].replace("``", ""),
                                epilog="Options override the config file; the defaults are the paper's grid.")
    p.add_argument("config", nargs="?", default=None, help="config file (.toml or .json) with ExperimentConfig keys")
    p.add_argument("--out", default=None, help="output directory (default runs/experiment)")
    p.add_argument("--scenarios", nargs="+", default=None, choices=SCENARIOS,
                   help=f"scenarios (default: {' '.join(SCENARIOS)})")
    p.add_argument("--tasks", nargs="+", default=None, metavar="TASK",
                   help="tasks (khgrl up --task), instead of the passage world's scenarios, e.g. fetch:control "
                        "fetch:moved (default: none)")
    p.add_argument("--methods", nargs="+", default=None, choices=tuple(METHOD_LABEL),
                   help=f"methods (default: {' '.join(REFERENCE_METHODS)}; a _noadapt method runs with --no-adapt: the "
                        "demonstrations' KMP in every scene)")
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="seeds (default 0 1 2 3 4)")
    p.add_argument("--episodes", type=int, default=None, help="episodes per run (default 60)")
    p.add_argument("--human-episodes", type=int, nargs="+", default=None,
                   help="1-based episodes with scripted corrections for KhGRL "
                        "(default: the paper's 4 5 10 19 20 28 29)")
    p.add_argument("--system", default=None, choices=SYSTEMS,
                   help="distributed (khgrl up, the default) or reference (single-process SB3)")
    p.add_argument("--jobs", type=int, default=None,
                   help="runs at a time (default 1; each run's learner uses one core)")
    p.add_argument("--max-lead", type=int, default=None, help="khgrl up --max-lead (default 8)")
    p.add_argument("--timeout", type=float, default=None, help="fail a run after this many seconds (default: none)")
    p.add_argument("--until-success", type=float, default=None, metavar="RATE",
                   help="end each run early once its last --success-window autonomous episodes succeed at RATE "
                        "(khgrl up --until-success; default 0: every episode)")
    p.add_argument("--success-window", type=int, default=None, help="autonomous episodes looked back over "
                                                                     "(default 20)")
    p.add_argument("--resume-interrupted", action="store_true",
                   help="continue an interrupted run from its learner checkpoint (khgrl up --resume) instead of "
                        "starting it again (default: off; experiment.json counts its parts)")
    p.add_argument("--up-args", default=None, metavar="FLAGS",
                   help="more khgrl up flags for every run, in one string, e.g. --up-args=\"--net-arch 64 64 "
                        "--batch-size 64\" (default: none; not the flags the grid sets itself)")
    p.add_argument("--dry-run", action="store_true",
                   help="list the runs, their state and commands; run nothing (default: off)")
    p.add_argument("--no-progress", action="store_true", help="plain lines instead of progress bars (default: off)")
    add_ray_arguments(p)
    p.set_defaults(func=run)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
