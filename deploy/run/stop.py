"""``khgrl stop``: stop a run, or press and release its e-stop, from any terminal (README, "On a real robot").

    khgrl stop RUN_DIR --now          # e-stop: every actor holds its robot within one control period (latched)
    khgrl stop RUN_DIR --release      # release the e-stop: the actors step again
    khgrl stop RUN_DIR                # stop the run: the actors end (their batches flushed), then khgrl up ends
    khgrl stop --run RUN --connect tls/HOST:7447 --zenoh-config launcher.json5 --now   # a run on other machines
    khgrl ready RUN_DIR               # --confirm-reset: the robot is ready, the next episode may start

It joins the run's router as the launcher (``RUN_DIR/config.json`` gives the run id and endpoint; a ``--secure``
run's launcher certificate is ``RUN_DIR/certs/zenoh/launcher.json5``: the router's access control lets only the
launcher publish on ``control/**``), publishes the command on ``control/actor`` (or ``control/<ID>``) every half
second, signed with the operator's key (``RUN_DIR/keys/operator-launcher.key`` or ``--key``: the actors refuse
control without it when the run has role keys, :mod:`khgrl.common.delivery.control_auth`), and waits until each
live actor's status confirms it (held by the e-stop, no longer held by it, no longer waiting for ready, or gone).

``khgrl ready`` is sent only when an actor's status says it waits for ready; the others are named, and when none waits
it says so and sends nothing (exit 1).

The e-stop is the run's one state (:mod:`khgrl.deploy.run.supervise`): ``--now`` and ``--release`` with RUN_DIR (and no
``--actor``) first write it to ``RUN_DIR/estop.json``, where an actor that starts or restarts reads it before its first
command, and the run's supervisor keeps what it hears. ``--now`` with no actor alive still presses it: confirmed by
that file or by the supervisor's heartbeat. The path to the first ``--now`` message is lean (no numpy, nothing but
Zenoh and msgpack loaded before it goes out): keystroke to held in README, "On a real robot".

Exit codes: 0 every actor confirmed (the e-stop: or the run's state recorded while no actor is alive); 1 the run has
ended (RUN_DIR/summary.json: said at once, the e-stop state still written), no router, no
actor alive, nothing waiting for ready, or an actor did not confirm within ``--timeout`` (named); 2 a bad argument (no
such run directory).

One module of ~310 lines on purpose: khgrl stop and khgrl ready share the same way to reach the actors and confirm
what they did.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

from khgrl.common.delivery.control_sign import OPERATOR, ControlSigner
from khgrl.common.delivery.declare import alive_now, put, subscribe
from khgrl.common.delivery.estop_state import write_state
from khgrl.common.delivery.transport import open_client, undeclare_all
from khgrl.common.wire.control import HEARTBEAT, HEARTBEAT_ESTOP, LAUNCHER
from khgrl.common.wire.keys import Keys

__all__ = ["main", "ready_main", "build_parser", "target"]

REPEAT_S = 0.5
STATUS_WAIT_S = 1.5  # khgrl ready: how long to wait for each actor's status (they come every second)


def build_parser(prog: str = "khgrl stop") -> argparse.ArgumentParser:
    """The parser of ``khgrl stop`` (or, with ``prog="khgrl ready"``, of ``khgrl ready``: no --now / --release).

    :param prog: the command's name.
    """
    ready = prog.endswith("ready")
    p = argparse.ArgumentParser(prog=prog, description="Say the robot is ready for the next episode (--confirm-reset)."
                                if ready else "Stop a run, or press / release its e-stop.")
    p.add_argument("run_dir", nargs="?", metavar="RUN_DIR", help="the run's directory (khgrl up's --run-dir): run id, "
                   "router endpoint and, for a --secure run, the launcher's certificate (default: --run/--connect)")
    if not ready:
        how = p.add_mutually_exclusive_group()
        how.add_argument("--now", action="store_true", help="press the e-stop: every actor holds its robot within "
                         "one control period until --release (default: stop the run)")
        how.add_argument("--release", action="store_true", help="release the e-stop (default: stop the run)")
    p.add_argument("--actor", default=None, help="only this actor (default: every actor)")
    p.add_argument("--run", default=None, help="the run id, without RUN_DIR (default: RUN_DIR's)")
    p.add_argument("--connect", default=None, help="the router's endpoint, without RUN_DIR (default: RUN_DIR's)")
    p.add_argument("--zenoh-config", default=None, help="a Zenoh configuration file with the launcher's certificate "
                   "(default: RUN_DIR/certs/zenoh/launcher.json5 for a --secure run, else none)")
    p.add_argument("--key", default=None, metavar="FILE", help="the operator's private signing key (default: "
                   "RUN_DIR/keys/operator-launcher.key if there, else the command goes unsigned)")
    p.add_argument("--timeout", type=float, default=None, help="seconds to wait for the actors to confirm (default: "
                   "5; a plain stop 20, for the actors' final flush)")
    return p


def target(args: argparse.Namespace) -> tuple[str, str, str | None]:
    """(run id, router endpoint, Zenoh configuration file) from RUN_DIR or the flags; raises ValueError.

    :param args: the parsed arguments.
    """
    run, connect, conf = args.run, args.connect, args.zenoh_config
    if args.run_dir:
        path = Path(args.run_dir) / "config.json"  # (read as JSON: no settings module, a quick --now)
        if not path.is_file():
            raise FileNotFoundError(f"run configuration {path} does not exist")
        data = json.loads(path.read_text())
        runtime = data.get("runtime") or {}
        run, connect = run or runtime.get("run") or data.get("run"), connect or runtime.get("endpoint")
        secure = Path(args.run_dir) / "certs" / "zenoh" / "launcher.json5"
        conf = conf or (str(secure) if runtime.get("secure") and secure.is_file() else None)
    if not run or not connect:
        raise ValueError("give RUN_DIR, or --run and --connect")
    return run, connect, conf


def _confirmed(command: str, alive: bool, held: str | None) -> bool:
    """Whether an actor has done ``command``: it is gone (``alive`` False), or its latest status (``held``; None: none
    since the command went out) says so."""
    if not alive:
        return True
    if command == "stop" or held is None:
        return False
    if command == "estop":
        return held.startswith("e-stop")
    if command == "release":
        return not held.startswith("e-stop")
    return not held.startswith("waiting for ready")  # ready


class _Actors:
    """The actors' latest ``held`` from their statuses (a Zenoh thread writes)."""

    def __init__(self) -> None:
        self.held: dict[str, str] = {}
        self.lock = threading.Lock()

    def on_status(self, sample) -> None:
        from khgrl.common.wire.messages import Status
        from khgrl.common.wire.protocol import ProtocolError, decode

        try:
            msg = decode(Status, sample.payload.to_bytes())
        except ProtocolError:
            return
        if msg.role == "actor":
            with self.lock:
                self.held[msg.info.id] = msg.info.held


def _wait(session, keys: Keys, actors: _Actors, command: str, target_key: str, want: list[str],
          timeout: float, signer: ControlSigner, seq: int = 0) -> list[str]:
    """Publish ``command`` (signed by ``signer``) every :data:`REPEAT_S` until each actor in ``want`` confirms; the
    ones that did not."""
    deadline, left, sent = time.monotonic() + timeout, list(want), seq > 0  # (seq > 0: the first went out already)
    while left and time.monotonic() < deadline:
        if not sent:
            put(session, target_key, signer.payload(target_key, command, LAUNCHER, seq), congestion="block",
                priority="interactive_high", express=True)
            seq += 1
        sent = False
        end = min(deadline, time.monotonic() + REPEAT_S)
        while left and time.monotonic() < end:
            time.sleep(0.05)
            alive = {k.split("/")[-1] for k in alive_now(session, keys.alive("actor", "*"), 0.5)}
            with actors.lock:
                left = [a for a in left if not _confirmed(command, a in alive, actors.held.get(a))]
    return left


def _waiting_for_ready(actors: _Actors, want: list[str], prog: str) -> list[str]:
    """``khgrl ready``: the actors of ``want`` that wait for ready (or have not said yet, within
    :data:`STATUS_WAIT_S`: statuses come every second); says which do not, and when none does."""
    deadline = time.monotonic() + STATUS_WAIT_S
    while time.monotonic() < deadline:
        with actors.lock:
            if all(a in actors.held for a in want):
                break
        time.sleep(0.05)
    with actors.lock:
        held = {a: actors.held.get(a) for a in want}
    waiting = [a for a, h in held.items() if h is None or h.startswith("waiting for ready")]
    for a in sorted(set(want) - set(waiting)):
        print(f"{a}: not waiting for ready ({held[a] or 'running'})")
    if not waiting:
        print(f"{prog}: nothing was waiting for ready: not sent", file=sys.stderr)
    return waiting


class _Supervisor:
    """The run's supervisor's latest heartbeat (``heartbeat`` or ``heartbeat-estop``; None: none heard)."""

    def __init__(self) -> None:
        self.said: str | None = None

    def on_control(self, sample) -> None:
        from khgrl.common.wire.messages import Control
        from khgrl.common.wire.protocol import ProtocolError, decode

        try:
            command = decode(Control, sample.payload.to_bytes()).command
        except ProtocolError:
            return
        if command in (HEARTBEAT, HEARTBEAT_ESTOP):
            self.said = command


def _record(args: argparse.Namespace, command: str, prog: str) -> Path | None:
    """``--now`` / ``--release`` with RUN_DIR (every actor): the run's e-stop state on disk first; its path."""
    if command not in ("estop", "release") or not args.run_dir or args.actor:
        return None
    try:
        return write_state(args.run_dir, command == "estop", f"{LAUNCHER} (khgrl stop)")
    except OSError as exc:
        print(f"{prog}: warning: the e-stop state not written in {args.run_dir}: {exc}", file=sys.stderr, flush=True)
        return None


def _no_actor(session, keys: Keys, command: str, recorded: Path | None, run: str, connect: str, prog: str,
              signer: ControlSigner) -> int:
    """No actor alive: an e-stop press or release is still the run's state -- confirmed by the file just written or
    by the supervisor's heartbeat (asked for :data:`REPEAT_S` * 3); the exit code."""
    if command in ("estop", "release"):
        sup = _Supervisor()
        sub = subscribe(session, keys.control("actor"), sup.on_control)
        try:
            want = HEARTBEAT_ESTOP if command == "estop" else HEARTBEAT
            for seq in range(1, 4):
                key = keys.control("actor")
                put(session, key, signer.payload(key, command, LAUNCHER, seq), congestion="block",
                    priority="interactive_high", express=True)
                end = time.monotonic() + REPEAT_S
                while sup.said != want and time.monotonic() < end:
                    time.sleep(0.02)
        finally:
            undeclare_all(sub)
        by = [w for w, ok in ((str(recorded), recorded is not None), ("the run's supervisor", sup.said == want)) if ok]
        if by:
            state = "pressed: an actor that starts holds" if command == "estop" else "released"
            print(f"{prog}: no actor of run {run} is alive at {connect}; the e-stop is {state} (kept in "
                  f"{' and by '.join(by)})")
            return 0
    print(f"{prog}: error: no actor of run {run} is alive at {connect}", file=sys.stderr)
    return 1


def _ended(run_dir: str | None, recorded: Path | None) -> str:
    """Why nothing answers, when RUN_DIR says the run is over (``RUN_DIR/summary.json``: ``khgrl up`` wrote it as
    the run ended): the run ended, not "the router is unreachable"; "" when RUN_DIR does not say so."""
    try:
        summary = json.loads((Path(run_dir) / "summary.json").read_text()) if run_dir else None
    except (OSError, ValueError):
        summary = None
    if not isinstance(summary, dict):
        return ""
    wall = summary.get("wall_time_s")
    said = f"run {summary.get('run')} has ended ({summary.get('ended', 'finished')}"
    said += f" after {wall:.0f} s" if isinstance(wall, (int, float)) else ""
    kept = f"; the e-stop state is kept in {recorded} for a --resume" if recorded else ""
    return f"{said}; {Path(run_dir) / 'summary.json'}): no process to stop{kept}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return _send(args, "estop" if args.now else "release" if args.release else "stop")


def ready_main(argv: list[str] | None = None) -> int:
    """``khgrl ready``: the robot is ready, the episode that waits for it may start."""
    return _send(build_parser("khgrl ready").parse_args(argv), "ready")


def _send(args: argparse.Namespace, command: str) -> int:
    """Send ``command`` to the run's actors until they confirm; the exit code."""
    prog = "khgrl ready" if command == "ready" else "khgrl stop"
    timeout = args.timeout if args.timeout is not None else 20.0 if command == "stop" else 5.0
    try:
        run, connect, conf = target(args)
        keys = Keys(run)
        signer = ControlSigner.load(args.run_dir, OPERATOR, args.key)
    except (ValueError, FileNotFoundError) as exc:  # (a bad key file: a RoleKeyError, a ValueError)
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if signer.key is None:  # (a run without role keys takes it; one with them refuses it)
        print(f"{prog}: warning: no operator key (RUN_DIR/keys/operator-launcher.key or --key): the command goes "
              f"unsigned, and the actors of a run with role keys refuse it", file=sys.stderr)
    recorded = _record(args, command, prog)
    if ended := _ended(args.run_dir, recorded):  # (--resume moves summary.json aside before anything starts)
        print(f"{prog}: {ended}", file=sys.stderr)
        return 1
    try:
        session = open_client(connect, timeout=5.0, zenoh_config=conf)
    except ConnectionError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    with session:
        t0, target_key, seq = time.monotonic(), keys.control(args.actor or "actor"), 0
        if command == "estop":  # at once, before anything else is asked or loaded
            put(session, target_key, signer.payload(target_key, command, LAUNCHER, 0), congestion="block",
                priority="interactive_high", express=True)
            seq = 1
        actors = _Actors()
        sub = subscribe(session, keys.status("actor", "*"), actors.on_status)
        try:
            want = sorted(k.split("/")[-1] for k in alive_now(session, keys.alive("actor", args.actor or "*"), 1.0))
            if not want:
                return _no_actor(session, keys, command, recorded, run, connect, prog, signer)
            if command == "ready":
                if not (want := _waiting_for_ready(actors, want, prog)):
                    return 1
                t0 = time.monotonic()
            left = _wait(session, keys, actors, command, target_key, want, timeout, signer, seq)
        finally:
            undeclare_all(sub)
    done = {"estop": "held by the e-stop", "release": "released", "stop": "stopped", "ready": "ready"}[command]
    for a in want:
        print(f"{a}: " + (f"not confirmed within {timeout:g} s" if a in left else done))
    print(f"{prog}: {command} "
          f"{'confirmed' if not left else 'NOT confirmed'} by {len(want) - len(left)} of "
          f"{len(want)} actors in {time.monotonic() - t0:.2f} s")
    return 1 if left else 0


if __name__ == "__main__":
    sys.exit(main())
