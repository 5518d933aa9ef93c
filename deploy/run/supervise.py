"""The run's supervisor (README, "On a real robot"; :mod:`khgrl.actor.supervision`): a heartbeat on
``control/actor`` every ``heartbeat_s`` carrying the run's e-stop state, which it keeps -- in memory and in
``RUN_DIR/estop.json`` -- from every press and release it hears for every actor (``khgrl stop --now`` / ``--release``
on ``control/actor`` or ``control/all``, a human-input client's e-stop; not ``khgrl stop --actor ID``'s, that actor's
alone) and from that file (``khgrl stop RUN_DIR --now`` writes it first). In robot mode an actor moves only
while it hears one.

``khgrl up`` supervises its own run (:class:`Heartbeat`, in robot mode). For processes started by hand (across
machines), the operator runs one next to ``khgrl stop``:

    khgrl supervise RUN_DIR                                   # the run's config.json: run id, endpoint, heartbeat_s
    khgrl supervise --run RUN --connect tls/HOST:7447 --zenoh-config launcher.json5 [--state-dir DIR]

It publishes as the launcher (a ``--secure`` run: the launcher's certificate, as ``khgrl stop``) until SIGINT or
SIGTERM; its end, like its crash, holds the robots (no heartbeat). Exit codes: 0 stopped; 1 no router; 2 a bad
argument.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from pathlib import Path

from khgrl.common.delivery.control_sign import OPERATOR, ControlSigner
from khgrl.common.delivery.declare import put, subscribe
from khgrl.common.delivery.estop_state import read_state, write_state
from khgrl.common.wire.control import HEARTBEAT, HEARTBEAT_ESTOP
from khgrl.common.wire.protocol import LAUNCHER, Keys

__all__ = ["Heartbeat", "run_supervisor", "main", "build_parser", "HEARTBEAT_S"]

log = logging.getLogger("khgrl.supervise")

HEARTBEAT_S = 0.1  # (safety.heartbeat_s's default)


class Heartbeat:
    """Publishes the heartbeat with the run's e-stop state from a thread; a context manager (module docstring).

    :param session: an open Zenoh session (the launcher's identity).
    :param keys: the run's key expressions.
    :param state_dir: where ``estop.json`` is kept (None: in memory only).
    :param period: seconds between heartbeats.
    :param say: called with a line when the state changes (default: the log).
    :param signer: the operator's signer (:class:`~khgrl.common.delivery.control_sign.ControlSigner`; default:
        unsigned, for a run without role keys).
    :param gate: the run's :class:`~khgrl.common.delivery.control_auth.ControlGate`: a press or release it refuses
        (unsigned, another role's key, a replay) does not change the run's state (default: none, nothing checked).
    """

    def __init__(self, session, keys: Keys, state_dir: Path | None, period: float = HEARTBEAT_S,
                 say=None, signer: ControlSigner | None = None, gate=None) -> None:
        self.session, self.keys, self.dir, self.period = session, keys, state_dir, period
        self.say = say or log.info
        self.signer = signer or ControlSigner(None, OPERATOR)  # signs the heartbeats (a run with role keys)
        self.gate = gate  # checks what it hears (a ControlGate; None: nothing checked)
        state = read_state(state_dir) if state_dir is not None else None
        self.pressed = bool(state and state.pressed)
        self.by = str(state.get("by")) if state else ""
        self.sent = 0
        self._stop = threading.Event()
        # the run's presses and releases: every actor's keys (one actor's, control/<id>, is that actor's alone)
        self._subs = [subscribe(session, keys.control(t), self._on_control, remote_only=True) for t in ("actor", "all")]
        self._subs.append(subscribe(session, keys.human_request("*"), self._on_control))
        self._thread = threading.Thread(target=self._run, name="heartbeat", daemon=True)

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _on_control(self, sample) -> None:
        from khgrl.common.wire.messages import Control
        from khgrl.common.wire.protocol import ProtocolError, decode

        try:
            msg = decode(Control, sample.payload.to_bytes())
        except ProtocolError:
            return
        if msg.command not in ("estop", "release"):  # (not the heartbeats of another supervisor)
            return
        if self.gate is not None and (why := self.gate.check(msg, str(sample.key_expr))):
            log.warning("%s on %s not taken: %s", msg.command, sample.key_expr, why)  # (the actors refuse it too)
            return
        self.note(msg.command == "estop", f"{msg.envelope.sender} on {sample.key_expr}")

    def note(self, pressed: bool, by: str) -> None:
        """A press or a release heard: the run's state (kept in ``estop.json``), sent with the next heartbeat.

        :param pressed: pressed (True) or released.
        :param by: who.
        """
        if pressed == self.pressed:
            return
        self.pressed, self.by = pressed, by
        if self.dir is not None:
            try:
                write_state(self.dir, pressed, by)
            except OSError as exc:
                log.error("e-stop state not written to %s: %s", self.dir, exc)
        self.say(f"e-stop {'pressed' if pressed else 'released'} by {by}")

    def _from_file(self) -> None:
        """``khgrl stop RUN_DIR`` writes the file before it publishes: a newer state there wins."""
        state = read_state(self.dir) if self.dir is not None else None
        if state is not None and state.pressed != self.pressed:
            self.pressed, self.by = state.pressed, str(state.get("by"))
            self.say(f"e-stop {'pressed' if self.pressed else 'released'} by {self.by} (the state file)")

    def beat(self) -> None:
        """One heartbeat (the state as it is now)."""
        self._from_file()
        key = self.keys.control("actor")
        put(self.session, key, self.signer.payload(key, HEARTBEAT_ESTOP if self.pressed else HEARTBEAT, LAUNCHER,
                                                   self.sent), congestion="drop", priority="interactive_high",
            express=True)
        self.sent += 1

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.beat()
            except Exception as exc:  # noqa: BLE001 - a closing session; the actors hold without heartbeats
                log.warning("heartbeat not sent: %s", exc)
            self._stop.wait(self.period)

    def close(self) -> None:
        """Stop the heartbeats (the actors hold after ``supervision_timeout``) and undeclare."""
        from khgrl.common.delivery.transport import undeclare_all

        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        undeclare_all(*self._subs)


def run_supervisor(session, keys: Keys, cfg, run_dir: Path, signer: ControlSigner | None = None):
    """``khgrl up``'s supervisor: a :class:`Heartbeat` when its actors need one (``safety.supervised``), else a context
    that does nothing.

    :param session: the launcher's session.
    :param keys: the run's key expressions.
    :param cfg: the run's settings.
    :param run_dir: the run directory (``estop.json``, ``keys/public.json``).
    :param signer: the operator's signer (default: unsigned).
    """
    from contextlib import nullcontext

    if not cfg.safety.supervised(cfg.stream.mode):
        return nullcontext()
    from khgrl.common.delivery.control_auth import ControlGate

    return Heartbeat(session, keys, run_dir, cfg.safety.heartbeat_s,
                     say=lambda line: print(f"khgrl up: {line}", file=sys.stderr, flush=True), signer=signer,
                     gate=ControlGate.of_run(run_dir))  # (its own: the launcher's gate takes the same messages)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl supervise", description="Supervise a run's actors: the heartbeat with the "
                                "run's e-stop state, without which an actor in robot mode holds its robot.")
    p.add_argument("run_dir", nargs="?", metavar="RUN_DIR", help="the run's directory: run id, router endpoint, "
                   "heartbeat_s, the launcher's certificate for a --secure run, and where estop.json is kept "
                   "(default: --run/--connect)")
    p.add_argument("--run", default=None, help="the run id, without RUN_DIR (default: RUN_DIR's)")
    p.add_argument("--connect", default=None, help="the router's endpoint, without RUN_DIR (default: RUN_DIR's)")
    p.add_argument("--zenoh-config", default=None, help="a Zenoh configuration file with the launcher's certificate "
                   "(default: RUN_DIR/certs/zenoh/launcher.json5 for a --secure run, else none)")
    p.add_argument("--key", default=None, metavar="FILE", help="the operator's private signing key (default: "
                   "RUN_DIR/keys/operator-launcher.key if there, else the heartbeats go unsigned)")
    p.add_argument("--state-dir", default=None, help="where to keep estop.json (default: RUN_DIR; without RUN_DIR: "
                   "in memory only)")
    p.add_argument("--heartbeat-s", type=float, default=None, help="seconds between heartbeats (default: RUN_DIR's "
                   f"safety.heartbeat_s, else {HEARTBEAT_S})")
    return p


def _period(args: argparse.Namespace) -> float:
    if args.heartbeat_s is not None:
        if not args.heartbeat_s > 0:
            raise ValueError("--heartbeat-s must be > 0")
        return args.heartbeat_s
    if args.run_dir:
        from khgrl.common.config.settings import read_run_file

        return read_run_file(Path(args.run_dir) / "config.json")[0].safety.heartbeat_s
    return HEARTBEAT_S


def main(argv: list[str] | None = None) -> int:
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.process import StopFlag, install_stop_handlers
    from khgrl.deploy.run.stop import target

    args = build_parser().parse_args(argv)
    try:
        run, connect, conf = target(args)
        keys, period = Keys(run), _period(args)
        signer = ControlSigner.load(args.run_dir, OPERATOR, args.key)
        state_dir = Path(args.state_dir or args.run_dir) if (args.state_dir or args.run_dir) else None
        if state_dir is not None and not state_dir.is_dir():
            raise FileNotFoundError(f"--state-dir {state_dir} is not a directory")
    except (ValueError, FileNotFoundError) as exc:
        print(f"khgrl supervise: error: {exc}", file=sys.stderr)
        return 2
    flag = StopFlag()
    install_stop_handlers(flag)
    try:
        session = open_client(connect, timeout=10.0, zenoh_config=conf, stop=lambda: bool(flag))
    except ConnectionError as exc:
        print(f"khgrl supervise: error: {exc}", file=sys.stderr)
        return 1 if not flag else 0
    from khgrl.common.delivery.control_auth import ControlGate

    beat = Heartbeat(session, keys, state_dir, period, say=lambda line: print(line, flush=True), signer=signer,
                     gate=ControlGate.of_run(args.run_dir))
    with session, beat:
        print(f"khgrl supervise: run {run} at {connect}: a heartbeat every {period:g} s (e-stop "
              f"{'pressed' if beat.pressed else 'released'})", flush=True)
        flag.event.wait()
    print(f"khgrl supervise: stopped ({flag.reason}) after {beat.sent} heartbeats: the actors hold", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
