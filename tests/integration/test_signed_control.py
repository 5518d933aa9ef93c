"""Issue 33, defect 3: control is authenticated in plain mode too (``common/delivery/control_auth.py``).

One plain ``khgrl up --mode robot`` of the passage world at 20 Hz, watched by this test's own Zenoh session (every
frame and actor status), is attacked by a process that cannot read the operator's key -- another user of the
machine reaching the loopback port -- and by processes that hold another role's key:

1. ``khgrl stop RUN_DIR --now`` holds a0. Then, on the router, with one put each: an unsigned ``release`` on
   ``control/actor`` with sender ``launcher``; an unsigned ``release`` on ``control/a0`` with sender ``mallory``; a
   ``release`` signed by a0's own key (as itself, and claiming to be the operator); a ``release`` signed by a human
   client's key (``khgrl keys RUN_DIR --human h9``, made while the run goes on) on ``control/actor``; an unsigned
   ``stop`` on ``control/all`` and ``ready`` on ``control/actor``. None of them moves the robot (no frame), stops an
   actor, the learner or the run (the launcher does not take the stop), and each is counted in a0's and the
   launcher's rejects.
   Before this fix the first put released the e-stop: frames came again at once (the issue: "releases the e-stop
   with one Zenoh put"), the unsigned ``stop`` ended a0 and the run, and the launcher printed them like genuine ones.
2. The operator's genuine ``khgrl stop --release`` works (recorded off the wire by this test); the human client h9
   presses the e-stop with its own key on its own request key (any admitted client may, assigned or not); the
   recorded genuine release, replayed, is refused (not newer than the operator's last: a replay); a fresh
   ``khgrl stop --release`` releases it; ``khgrl stop`` ends the run.
"""

from __future__ import annotations

import subprocess
import threading
import time

import pytest

from helpers import read_json, wait_for
from launch import FAST, UP, Launcher, _env

pytestmark = pytest.mark.integration

RATE = 20.0
ARGS = [*FAST, "--method", "khgrl", "--human", "none", "--episodes", "60", "--seed", "3", "--mode", "robot",
        "--rate", str(RATE)]
QUIET_S = 1.0  # after the attacks: this long without a frame means the robot stayed held


def _khgrl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*UP[:-1], *args], env=_env(), capture_output=True, text=True, timeout=60)


class Tap:
    """a0's frames (arrival times), its statuses' ``held``, and every control payload on the router."""

    def __init__(self, session, keys) -> None:
        self.frames: list[float] = []
        self.held: list[tuple[float, str]] = []
        self.control: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()

        def on_status(sample) -> None:
            from khgrl.common.wire.messages import Status
            from khgrl.common.wire.protocol import decode

            with self.lock:
                self.held.append((time.time(), decode(Status, sample.payload.to_bytes()).info.held))

        def on_control(sample) -> None:
            with self.lock:
                self.control.append((str(sample.key_expr), sample.payload.to_bytes()))

        self.subs = [session.declare_subscriber(keys.frame("a0"), lambda s: self.frames.append(time.time())),
                     session.declare_subscriber(keys.status("actor", "a0"), on_status),
                     session.declare_subscriber(keys.control("**"), on_control)]

    def frames_since(self, t0: float) -> int:
        return sum(t >= t0 for t in list(self.frames))

    def said(self, text: str, since: float) -> bool:
        with self.lock:
            return any(h.startswith("e-stop by") and text in h for t, h in self.held if t >= since)

    def last_release(self) -> tuple[str, bytes]:
        from khgrl.common.wire.messages import Control
        from khgrl.common.wire.protocol import decode

        with self.lock:
            return [(k, p) for k, p in self.control if decode(Control, p).command == "release"][-1]


def _keyless(keys) -> list[tuple[str, bytes]]:
    """(key, payload) of each unsigned control message of part 1: what anyone on the router can put."""
    from khgrl.common.wire.messages import Control
    from khgrl.common.wire.protocol import LAUNCHER, encode

    return [(keys.control("actor"), encode(Control(command="release"), LAUNCHER, 100)),
            (keys.control("a0"), encode(Control(command="release"), "mallory", 0)),
            (keys.control("all"), encode(Control(command="stop"), LAUNCHER, 101)),
            (keys.control("actor"), encode(Control(command="ready"), "mallory", 1))]


def _wrong_role(run_dir, keys) -> list[tuple[str, bytes]]:
    """(key, payload) of each release signed with another role's key: a0's own, and a human client's."""
    from khgrl.common.delivery.control_auth import OPERATOR, ControlSigner
    from khgrl.common.delivery.role_keys import load_private, private_path
    from khgrl.common.wire.protocol import LAUNCHER

    made = _khgrl("keys", str(run_dir), "--human", "h9")  # a human client's key, made while the run goes on
    assert made.returncode == 0 and "human:h9: made" in made.stdout, made.stdout + made.stderr
    actor_key = load_private(None, "actor:a0", private_path(run_dir, "actor:a0"))
    as_actor, actor_as_operator = ControlSigner(actor_key, "actor:a0"), ControlSigner(actor_key, OPERATOR)
    human = ControlSigner.load(run_dir, "human:h9")
    out = [(keys.control("actor"), signer.payload(keys.control("actor"), "release", sender, 1))
           for signer, sender in ((as_actor, "a0"), (actor_as_operator, LAUNCHER), (human, "h9"))]
    return out + [(keys.human_request("h9"), human.payload(keys.human_request("h9"), "release", "h9", 2))]


def _attack(session, tap: "Tap", up: Launcher, held: float, attacks: list[tuple[str, bytes]], what: str) -> None:
    """Put each attack once; then no frame for :data:`QUIET_S`, the launcher alive, a0 still held by the e-stop."""
    for key, payload in attacks:
        session.put(key, payload)
    time.sleep(QUIET_S)
    assert tap.frames_since(held) == 0, f"{what} control moved the robot"
    # (held by the launcher's press, or first by the supervisor's heartbeat that carries it)
    assert up.proc.poll() is None and tap.said("e-stop by", held), (what, up.stdout, up.stderr)


@pytest.mark.timeout(240)
def test_keyless_and_wrong_role_control_cannot_release_stop_or_ready_a_robot(tmp_path):
    from khgrl.common.delivery.control_auth import ControlSigner
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys

    up = Launcher(tmp_path, tmp_path / "run", *ARGS)
    session = None
    try:
        wait_for(lambda: (up.run_dir / "config.json").exists() and up.proc.poll() is None, 60, "config.json")
        runtime = read_json(up.run_dir / "config.json")["runtime"]
        keys = Keys(runtime["run"])
        session = open_client(runtime["endpoint"], timeout=10)  # plain: no key, as another user of the machine
        tap = Tap(session, keys)
        wait_for(lambda: len(tap.frames) > 20, 90, "a0's frames")
        press = _khgrl("stop", str(up.run_dir), "--now")
        assert press.returncode == 0 and "a0: held by the e-stop" in press.stdout, press.stdout + press.stderr
        held = time.time()
        attacks = _keyless(keys)
        _attack(session, tap, up, held, attacks[:2], "a keyless")  # (before the fix: the first put released a0)
        _attack(session, tap, up, held, attacks[2:], "a keyless stop or ready")  # (before: a0 and the run ended)
        attacks += _wrong_role(up.run_dir, keys)
        _attack(session, tap, up, held, attacks[4:], "another role's")

        # part 2: the operator releases; any admitted client presses; a recorded release replayed does nothing
        release = _khgrl("stop", str(up.run_dir), "--release")
        assert release.returncode == 0 and "a0: released" in release.stdout, release.stdout + release.stderr
        wait_for(lambda: tap.frames_since(time.time() - 0.5) > 3, 10, "frames after the operator's release")
        recorded = tap.last_release()
        h9 = ControlSigner.load(up.run_dir, "human:h9")
        session.put(keys.human_request("h9"), h9.payload(keys.human_request("h9"), "estop", "h9", 10))
        wait_for(lambda: tap.said("human client h9", time.time() - 1.0), 10, "h9's e-stop")
        pressed = time.time()
        session.put(*recorded)  # the genuine release, replayed
        time.sleep(QUIET_S)
        assert tap.frames_since(pressed + 0.1) == 0, "a replayed release moved the robot"
        release = _khgrl("stop", str(up.run_dir), "--release")
        assert release.returncode == 0 and "a0: released" in release.stdout, release.stdout + release.stderr
        stop = _khgrl("stop", str(up.run_dir))
        assert stop.returncode == 0 and "a0: stopped" in stop.stdout, stop.stdout + stop.stderr
        up.proc.wait(timeout=60)
    finally:
        if session is not None:
            session.close()
        up.cleanup()
    summary = read_json(up.run_dir / "actor-a0" / "summary.json")
    refused = summary["rejects"].get("control", 0)
    assert refused >= len(attacks) + 1, summary["rejects"]  # every attack and the replay, counted
    log = (up.run_dir / "actor-a0" / "actor.log").read_text()
    for why in ("not signed", "only the operator", "wrong signature", "a replay"):
        assert why in log, why
    assert "from another session (sender 'mallory')" not in up.stderr and "stopped by a stop command" in up.stderr
    launcher = read_json(up.run_dir / "summary.json")["launcher_rejects"].get("control", 0)
    assert launcher >= 7, launcher  # khgrl up refused them too (the 7 on control/*, and the replay)
    assert "stop not signed" in (up.run_dir / "learner" / "learner.log").read_text()  # the learner refused the stop
    print(f"refused control: {refused} (attacks {len(attacks)} + 1 replay); e-stop held through all of them")
