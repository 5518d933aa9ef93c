"""``khgrl up``: one run on this machine -- a Zenoh router, the learner, the actors and (KhGRL) a human-input
client, each its own OS process reading the run's resolved configuration (``RUN_DIR/config.json``) -- with a
live progress view, stopped cleanly when the actors finish, on Ctrl-C/SIGTERM, on a stop command, at
``--timeout``, or when a process fails (reported with its exit code and the tail of its log).

The run directory (layout: :mod:`khgrl.deploy.run.rundir`) is refused if it already holds a run, unless ``--resume``
(continue it: episode numbering, episodes.csv, corrections.csv and the learner's checkpoint carry on) or
``--overwrite`` (delete the earlier run first). Children are spawned by
:class:`khgrl.deploy.run.supervisor.ProcessGroup`
and die with the launcher (parent-death signal), even if it is killed. ``--secure`` runs everything over mutual
TLS with access control per process (certificates made in ``RUN_DIR/certs``: :mod:`khgrl.deploy.run.secure`);
``--zenoh-config FILE`` gives every process a Zenoh configuration file.

``RUN_DIR/run.key`` gets a new secret first (0600; kept on ``--resume``): the learner signs acks and weights with it,
actors check them (:mod:`khgrl.common.delivery.run_key`), and ``RUN_DIR/keys`` a signing key per process (control:
:mod:`khgrl.common.delivery.control_auth`). An actor's alarm in its status (another process publishes as it, two
learners) ends the run with that line as its error (:mod:`khgrl.deploy.run.outcome`). In robot mode it supervises
(:mod:`khgrl.deploy.run.supervise`).

Exit codes: 0 the actors finished; 1 a process failed, an actor's alarm, the router was unreachable, ``--timeout``
or a stop command from elsewhere; 2 a bad configuration or run directory; 128 + signal number on SIGINT/SIGTERM.

One module of ~390 lines on purpose: the command's parser, the plan of a run and the run itself read top to bottom
as one story; its parts with another job are already apart (preflight, rundir, outcome, progress, supervise).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from khgrl.common.config.hilserl import recipe_runtime
from khgrl.common.config.settings import HUMAN_METHODS, RunConfig, add_config_flags, resolve, write_run_config
from khgrl.common.delivery import control_auth, role_keys, run_key
from khgrl.common.delivery.declare import put, subscribe
from khgrl.common.delivery.task_link import TASK_FILE, save_task
from khgrl.common.delivery.transport import Inbox, free_port, open_client, undeclare_all, wait_reachable
from khgrl.common.delivery.zenoh_config import config_file
from khgrl.common.process import StopFlag, install_stop_handlers
from khgrl.common.wire.control import HEARTBEATS
from khgrl.common.wire.messages import Control, EpisodeReport, Status
from khgrl.common.wire.protocol import LAUNCHER, Keys, ProtocolError, RejectCounter, decode
from khgrl.deploy.run import outcome, rundir
from khgrl.deploy.run.outcome import Outcome, ending, exit_code, final_line, report_failures, write_summary
from khgrl.deploy.run.preflight import check_task
from khgrl.deploy.run.progress import ProgressView
from khgrl.deploy.run.rundir import RunDirError
from khgrl.deploy.run.secure import SecureRun, prepare_secure_run, run_identities
from khgrl.deploy.run.supervise import run_supervisor
from khgrl.deploy.run.supervisor import Proc, ProcessGroup, khgrl_argv
from khgrl.deploy.run.view_sink import RunView, add_view_flags, run_view
from khgrl.learner.algorithm import check_algorithm

__all__ = ["main", "build_parser", "RunPlan", "plan_run"]

FAILURE_GRACE_S = 5.0  # after a failure or an interrupt: how long children get for the stop command
ACTOR_STOP_GRACE_S = 8.0  # actors stop first: their last batches go into the learner's final checkpoint
SIGNAL_GRACE_S = 10.0  # then SIGINT, and SIGKILL after this many seconds more


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="khgrl up", description="Launch router, learner, actor(s) and human-input process locally.",
        epilog="Settings: defaults < --config FILE < flags. The resolved configuration is written to "
               "RUN_DIR/config.toml; khgrl up --config RUN_DIR/config.toml runs it again.")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="run configuration (TOML, e.g. an earlier RUN_DIR/config.toml; default: none)")
    again = p.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue the run in RUN_DIR from its learner checkpoint and episode count; without "
                            "--config its config.toml is the base configuration (default: off)")
    again.add_argument("--overwrite", action="store_true",
                       help="delete an earlier run in RUN_DIR first (default: off: such a directory is refused)")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                   help="live progress table on a terminal (stdout elsewhere, e.g. a file: a line per episode and "
                        "the table at the end); --no-progress: a line per episode only (default: on)")
    net = p.add_mutually_exclusive_group()
    net.add_argument("--secure", action="store_true",
                     help="mutual TLS and access control per process: a CA and a certificate for each process are "
                          "made in RUN_DIR/certs, the router listens on tls/ and lets each identity publish only "
                          "its own keys (default: off: plain TCP on loopback)")
    net.add_argument("--zenoh-config", default=None, metavar="FILE",
                     help="a Zenoh configuration (JSON5) for the router and every process, merged under KhGRL's "
                          "required settings; examples in deploy/zenoh/ (default: $ZENOH_CONFIG if set, else none)")
    add_config_flags(p)
    add_view_flags(p)  # --view, --view-camera-every (deploy/run/view_sink.py)
    return p


# ------------------------------------------------------------------------------------ the plan
@dataclass
class RunPlan:
    """What a start of ``khgrl up`` runs: the resolved settings and the run's runtime facts."""

    cfg: RunConfig
    run_dir: Path
    run_id: str
    endpoint: str
    resume: bool = False
    overwrite: bool = False
    progress: bool = True
    argv: list[str] = field(default_factory=list)
    previous: dict = field(default_factory=dict)  # runtime of the part before (resume)
    task: Any = None  # the run's TaskDescriptor (the learner gets it from RUN_DIR/learner/task.msgpack)
    secure: bool = False  # --secure: mTLS + access control (certificates in RUN_DIR/certs)
    zenoh_config: str | None = None  # --zenoh-config for every process (not with --secure)
    secure_run: SecureRun | None = None  # made by prepare_run_dir with --secure
    bounds: dict = field(default_factory=dict)  # the task's value bounds: stated or derived (with the rule)

    def zenoh_file(self, role: str, ident: str | None = None) -> str | None:
        """The Zenoh configuration of a process (its own identity's with --secure), or None."""
        return self.secure_run.config_for(role, ident) if self.secure_run is not None else self.zenoh_config

    def zenoh_args(self, role: str, ident: str | None = None) -> list[str]:
        """``--zenoh-config FILE`` for a process, or nothing."""
        file = self.zenoh_file(role, ident)
        return ["--zenoh-config", file] if file else []

    @property
    def config_json(self) -> Path:
        return self.run_dir / "config.json"


def _resolve_config(args: argparse.Namespace) -> RunConfig:
    """Defaults < --config < flags; on ``--resume`` without ``--config``: RUN_DIR/config.toml is the file."""
    cfg = resolve(args.config, args)
    if not args.resume or args.config:
        return cfg
    base = Path(cfg.run_dir) / "config.toml"
    if not base.is_file():
        raise RunDirError(f"--resume: nothing to resume in {cfg.run_dir}: it has no config.toml")
    return resolve(base, args, overrides={"run_dir": cfg.run_dir})


def _check_run_dir(run_dir: Path, args: argparse.Namespace, checkpoint_dir: str = "") -> None:
    found = rundir.results_in(run_dir)
    if args.resume:
        if not (run_dir / "config.toml").is_file():
            raise RunDirError(f"--resume: nothing to resume in {run_dir}: it has no config.toml")
        if not rundir.has_checkpoint(run_dir, checkpoint_dir):
            raise RunDirError(f"--resume: nothing to resume in {run_dir}: no learner checkpoint "
                              f"(learner/checkpoint/state.json); start it again with --overwrite")
    elif found and not args.overwrite:
        raise RunDirError(f"run directory {run_dir} already holds a run ({', '.join(found)}): give --resume to "
                          f"continue it, --overwrite to delete it and start again, or another --run-dir")
    elif found:
        rundir.refuse_live(run_dir)  # --overwrite deletes only a run that has ended


def plan_run(args: argparse.Namespace, argv: list[str]) -> RunPlan:
    """Resolve the configuration and check the run directory (nothing is written yet).

    :param args: parsed ``khgrl up`` arguments
    :param argv: the command line, recorded in config.json
    :raises RunDirError: the run directory cannot be used as asked
    :raises ValueError: a bad setting"""
    cfg = _resolve_config(args)
    if cfg.demos:
        cfg = dataclasses.replace(cfg, demos=rundir.resolve_demos(cfg.demos))
    run_dir = Path(cfg.run_dir)
    _check_run_dir(run_dir, args, cfg.checkpoint_dir)
    check_algorithm(cfg.algo)
    bounds: dict = {}  # the task's value bounds and how they came about (config.json: runtime.task_bounds)
    task = check_task(cfg, bounds)
    previous = rundir.previous_runtime(run_dir) if args.resume else {}
    run_id = cfg.run or str(previous.get("run") or "") or rundir.make_run_id(run_dir)
    Keys(run_id)  # a valid key chunk (ValueError otherwise)
    if args.secure and cfg.connect:
        raise ValueError("--secure starts its own router with certificates made for the run; to join a router "
                         "elsewhere give --connect with --zenoh-config (README: Running across machines)")
    scheme = "tls" if args.secure else "tcp"
    endpoint = cfg.connect or f"{scheme}/127.0.0.1:{cfg.port or free_port()}"
    return RunPlan(cfg=cfg, run_dir=run_dir, run_id=run_id, endpoint=endpoint, resume=args.resume,
                   overwrite=args.overwrite, progress=args.progress, argv=argv, previous=previous, task=task,
                   secure=args.secure, zenoh_config=config_file(args.zenoh_config), bounds=bounds)


def prepare_run_dir(plan: RunPlan) -> None:
    """Clear (``--overwrite``) or archive the part before (``--resume``), then write the configuration files.

    :param plan: the run's plan"""
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    part = 1
    if plan.overwrite:
        deleted = rundir.clear_run(plan.run_dir)
        if deleted:
            print(f"khgrl up: --overwrite: deleted the earlier run in {plan.run_dir} ({', '.join(deleted)})",
                  flush=True)
    if plan.resume:
        part = int(plan.previous.get("part", 1)) + 1
        rundir.archive_part(plan.run_dir, part - 1)
    if plan.cfg.demos and not plan.resume:  # the run keeps the demonstrations it was trained from
        kept = rundir.keep_demos(plan.run_dir, plan.cfg.task_spec, plan.cfg.demos)
        plan.cfg = dataclasses.replace(plan.cfg, demos=str(kept))
    run_key.create(plan.run_dir, fresh=not plan.resume)  # the learner signs acks and weights, actors check
    role_keys.make_run_keys(plan.run_dir, run_identities(plan.cfg), fresh=not plan.resume)  # the operator signs control
    if plan.secure:
        plan.secure_run = prepare_secure_run(plan.run_dir, plan.endpoint, run_identities(plan.cfg))
    runtime = {"run": plan.run_id, "endpoint": plan.endpoint, "cwd": os.getcwd(), "actor_ids": plan.cfg.actor_ids(),
               "argv": plan.argv, "started": started, "resumed": plan.resume, "part": part,
               "first_started": plan.previous.get("first_started", plan.previous.get("started", started)),
               "secure": plan.secure, "task_bounds": plan.bounds, **recipe_runtime(plan.cfg)}
    write_run_config(plan.run_dir, plan.cfg, runtime)
    # the learner builds its spaces from the task at once (instead of waiting for an actor to announce it), so it
    # is up before the actors step, as a learner of any task must be for a seeded run to repeat
    task_file = plan.run_dir / "learner" / TASK_FILE
    if plan.task is not None and not task_file.is_file():
        save_task(task_file, plan.task)


# ------------------------------------------------------------------------------------ the run
class Run:
    """Starts the processes, shows progress, and stops them: one start of ``khgrl up``.

    :param plan: the run's plan (configuration files already written)
    :param group: the process group the children are started in
    :param flag: set by SIGINT/SIGTERM
    :param view: the run's Rerun view (``--view``; it logs the learner's statuses), or None
    """

    def __init__(self, plan: RunPlan, group: ProcessGroup, flag: StopFlag, view: RunView | None = None) -> None:
        self.plan, self.cfg, self.group, self.flag, self.view = plan, plan.cfg, group, flag, view or RunView()
        self.keys = Keys(plan.run_id)
        self.inbox = Inbox(maxsize=10_000, overflow="drop_oldest")
        self.rejects = RejectCounter("launcher")
        self.signer, self.gate = control_auth.operator_side(plan.run_dir)  # signs and checks control
        self.out = Outcome()
        self.actors: list[Proc] = []

    def execute(self) -> Outcome:
        """Run until done, then stop every process (the group's SIGINT/SIGKILL fallback included)."""
        try:
            self._start_router()
            self._start_children()
            print(f"khgrl up: run {self.plan.run_id} on {self.plan.endpoint}; logs in {self.group.log_dir}",
                  flush=True)
            with open_client(self.plan.endpoint, self.cfg.stream.lease_ms, stop=lambda: bool(self.flag),
                             timeout=self.cfg.connect_timeout,
                             zenoh_config=self.plan.zenoh_file("launcher")) as session:
                self._supervise(session)
        except ConnectionError as exc:
            if not self.flag:
                self.out.error = str(exc)
        finally:
            self.group.stop_all(grace=SIGNAL_GRACE_S, kill_after=5.0)
        self.out.rejects = self.rejects.by_kind()
        return self.out

    def _start_router(self) -> None:
        if self.cfg.connect:
            return
        router = self.group.start("router", khgrl_argv("router", "--listen", self.plan.endpoint,
                                                       "--lease-ms", str(self.cfg.stream.lease_ms),
                                                       *self.plan.zenoh_args("router")))
        try:
            wait_reachable(self.plan.endpoint, self.cfg.connect_timeout,
                           stop=lambda: bool(self.flag) or router.poll() is not None)
        except ConnectionError:
            if router.poll() is not None:
                self.out.failed.append("router")
            raise

    def _start_children(self) -> None:
        if self.flag:
            raise ConnectionError("stopped before the processes started")
        config = str(self.plan.config_json)
        resume = ["--resume"] if self.plan.resume else []
        zargs = self.plan.zenoh_args
        self.group.start("learner", khgrl_argv("learner", "--config", config, *resume, *zargs("learner")))
        for aid in self.cfg.actor_ids():
            self.actors.append(self.group.start(aid, khgrl_argv("actor", "--config", config, "--id", aid, *resume,
                                                                *zargs("actor", aid))))
        if self.cfg.method in HUMAN_METHODS and self.cfg.human != "none":
            h = self.cfg.human
            self.group.start(f"human-{h}", khgrl_argv("human", h, "--config", config, "--id", h, *zargs("human", h)))
        rundir.write_pids(self.plan.run_dir, os.getpid(), {p.name: p.pid for p in self.group.procs})

    def _supervise(self, session) -> None:
        subs = [subscribe(session, self.keys.episode("*"), self.inbox.callback("episode")),
                subscribe(session, self.keys.status("learner", "*"), self.inbox.callback("status")),
                subscribe(session, self.keys.status("actor", "*"), self.inbox.callback("status")),
                # only other sessions' commands: this launcher's own stop never counts as one from elsewhere
                subscribe(session, self.keys.control("**"), self.inbox.callback("control"), remote_only=True)]
        try:  # (in robot mode the actors move only while they hear this launcher's heartbeat)
            with run_supervisor(session, self.keys, self.cfg, self.plan.run_dir, self.signer):
                with ProgressView(self.cfg.actor_ids(), self.cfg.episodes, self.plan.progress,
                                  schedule_quiet=self.cfg.stream.mode == "simulation") as view:
                    self._watch(view)
                self._stop_children(session)
        finally:
            undeclare_all(*subs)

    def _watch(self, view: ProgressView) -> None:
        deadline = time.monotonic() + self.cfg.timeout if self.cfg.timeout > 0 else None
        while not self.flag:
            item = self.inbox.get(timeout=0.25)
            if item is not None:
                self._handle(item, view)
            if self._finished() or self.out.stopped_by or self.out.error:
                return
            if deadline is not None and time.monotonic() > deadline:
                print(f"khgrl up: timeout after {self.cfg.timeout:g} s", flush=True)
                self.out.failed.append("timeout")
                return

    def _handle(self, item: tuple, view: ProgressView) -> None:
        kind, key, payload, _ = item
        try:
            if kind == "episode":
                view.episode(decode(EpisodeReport, payload))
            elif kind == "status":
                status = decode(Status, payload)
                view.status(status)
                self.view.status(status)
                outcome.actor_alarm(self.out, status, key)
            else:
                self._control(decode(Control, payload), key)
        except ProtocolError as exc:
            self.rejects.reject(kind, key, exc)

    def _control(self, msg: Control, key: str) -> None:
        """A control command from another session, signed by the operator's key (else refused, counted): reported
        (not a supervisor's heartbeats); a stop ends the run as stopped from elsewhere (exit 1)."""
        self.gate.admit(msg, key)
        if msg.command not in HEARTBEATS:
            print(f"khgrl up: control {msg.command!r} on {key} from another session (sender "
                  f"{msg.envelope.sender!r})", file=sys.stderr, flush=True)
        if msg.command == "stop" and not self.out.stopped_by:
            self.out.stopped_by = f"a stop command from {msg.envelope.sender!r} on {key}"
            print(f"khgrl up: stopped by {self.out.stopped_by}", file=sys.stderr, flush=True)

    def _finished(self) -> bool:
        """Whether to stop: a process failed, or every actor finished."""
        for p in self.group.procs:
            if p.essential and p.poll() not in (None, 0) and p.name not in self.out.failed:
                self.out.failed.append(p.name)
                outcome.process_error(self.out, p)
        return bool(self.out.failed) or all(p.poll() == 0 for p in self.actors)

    def _stop_children(self, session) -> None:
        """Actors first, then everything else: ``control/actor stop`` until the actors exited (each publishes its last
        batch, waits a moment for the learner to checkpoint it) or :data:`ACTOR_STOP_GRACE_S`, then ``control/all stop``
        until all but the router exited or the grace is over (then :meth:`execute` signals them); each second again."""
        abrupt = bool(self.out.failed) or bool(self.flag)
        grace = min(self.cfg.stop_timeout, FAILURE_GRACE_S + ACTOR_STOP_GRACE_S) if abrupt else self.cfg.stop_timeout
        deadline = time.monotonic() + grace
        others = [p for p in self.group.procs if p.name != "router"]
        first = min(deadline, time.monotonic() + ACTOR_STOP_GRACE_S)
        phases = ((self.actors, "actor", first), (others, "all", deadline))
        seq = 0
        for procs, target, until in phases:
            while True:
                put(session, k := self.keys.control(target), self.signer.payload(k, "stop", LAUNCHER, seq))
                seq += 1
                left = until - time.monotonic()
                if self.group.wait_all(max(0.0, min(1.0, left)), procs) or left <= 0:
                    break


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    flag = StopFlag()
    install_stop_handlers(flag)
    try:
        plan = plan_run(args, ["khgrl", "up", *argv])
        view = run_view(args, plan)  # --view: checked before anything is written
        if plan.cfg.connect:  # fail fast (ConnectionError naming it) if nothing listens there
            wait_reachable(plan.endpoint, plan.cfg.connect_timeout, stop=lambda: bool(flag))
        prepare_run_dir(plan)
    except (RunDirError, ValueError, FileNotFoundError) as exc:
        print(f"khgrl up: error: {exc}", file=sys.stderr)
        return 2
    except ConnectionError as exc:
        print(f"khgrl up: error: {exc}", file=sys.stderr)
        return exit_code(Outcome(error=str(exc)), flag)
    t0 = time.monotonic()
    with view, ProcessGroup(plan.run_dir / "logs", env=view.env()) as group:  # (the view outlives the processes)
        out = Run(plan, group, flag, view).execute()
        wall = time.monotonic() - t0
        write_summary(plan, group, out, wall, bool(flag), ending(out, flag))
        report_failures(group, out)
    codes = {p.name: p.returncode for p in group.procs}
    print(final_line(out, flag, wall, codes, plan.run_dir), flush=True)
    return exit_code(out, flag)


if __name__ == "__main__":
    sys.exit(main())
