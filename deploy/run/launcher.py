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

The plan of a run (settings, run directory, configuration files) is :mod:`khgrl.deploy.run.plan`; here are the
command's parser, the run itself (start, watch, stop) and ``main``.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time

from khgrl.common.config.settings import HUMAN_METHODS, add_config_flags
from khgrl.common.delivery import control_auth
from khgrl.common.delivery.declare import put, subscribe
from khgrl.common.delivery.transport import Inbox, open_client, undeclare_all, wait_reachable
from khgrl.common.process import StopFlag, install_stop_handlers
from khgrl.common.wire.control import HEARTBEATS
from khgrl.common.wire.messages import Control, EpisodeReport, Status
from khgrl.common.wire.protocol import LAUNCHER, Keys, ProtocolError, RejectCounter, decode
from khgrl.deploy.run import outcome, rundir
from khgrl.deploy.run.outcome import Outcome, ending, exit_code, final_line, report_failures, write_summary
from khgrl.deploy.run.plan import RunPlan, plan_run, prepare_run_dir
from khgrl.deploy.run.progress import ProgressView
from khgrl.deploy.run.rundir import RunDirError
from khgrl.deploy.run.supervise import run_supervisor
from khgrl.deploy.run.supervisor import Proc, ProcessGroup, khgrl_argv
from khgrl.deploy.run.view_sink import RunView, add_view_flags, run_view

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
        self.heard: set[str] = set()  # the learner and actors whose status arrived: they take the stop command

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
                self.heard.add("learner" if status.role == "learner" else key.rsplit("/", 1)[-1])
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
        until all but the router exited or the grace is over (then :meth:`execute` signals them); each second again.
        On an abrupt stop, the learner or an actor not heard from yet gets SIGINT first."""
        abrupt = bool(self.out.failed) or bool(self.flag)
        grace = min(self.cfg.stop_timeout, FAILURE_GRACE_S + ACTOR_STOP_GRACE_S) if abrupt else self.cfg.stop_timeout
        if abrupt:  # one still starting has not subscribed to the stop command: SIGINT (its clean stop) at once
            for p in self.group.procs:
                if p.name in {*self.cfg.actor_ids(), "learner"} - self.heard and p.poll() is None:
                    p.signal(signal.SIGINT)
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
