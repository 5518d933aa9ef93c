"""The parts of supervision and the run's e-stop state without processes (tests/integration/test_supervision.py runs
them for real): the lean control payload, ``estop.json``, the heartbeat's timing rules, a client's repeated press."""

from __future__ import annotations

import time

import pytest
from khgrl.actor.supervision import Supervision, heartbeat_refusal
from khgrl.common.delivery.estop_state import read_state, write_state
from khgrl.common.wire.control import HEARTBEAT_ESTOP, control_payload
from khgrl.common.wire.messages import Control
from khgrl.common.wire.protocol import decode, encode


@pytest.mark.parametrize("command", ["estop", "release", "stop", "ready", HEARTBEAT_ESTOP])
def test_control_payload_is_the_protocols_encoding(command):
    """``khgrl stop --now``'s numpy-free payload is byte for byte what ``encode`` makes, and decodes."""
    assert control_payload(command, "launcher", 7, ts=12.5) == encode(Control(command=command), "launcher", 7, ts=12.5)
    assert decode(Control, control_payload(command, "launcher", 7)).command == command


def test_estop_state_file(tmp_path):
    """No file: never pressed; written atomically; a file that cannot be read counts as pressed."""
    assert read_state(tmp_path) is None
    write_state(tmp_path, True, "launcher")
    assert read_state(tmp_path).pressed and read_state(tmp_path)["by"] == "launcher"
    write_state(tmp_path, False, "launcher")
    assert not read_state(tmp_path).pressed and [p.name for p in tmp_path.iterdir()] == ["estop.json"]
    (tmp_path / "estop.json").write_text("{half")
    assert read_state(tmp_path).pressed and "cannot be read" in read_state(tmp_path)["by"]
    (tmp_path / "estop.json").write_text('{"pressed": "no"}')
    assert read_state(tmp_path).pressed


def test_supervision_waits_then_detects_silence():
    """Required: held until a first heartbeat; lost once the last one is older than the timeout; a heartbeat-estop
    within the timeout of a release is stale. Not required: never waits, never lost."""
    s = Supervision(True, 0.4)
    assert s.waiting and s.silence(10.0) is None
    s.beat(10.0)
    assert not s.waiting and s.silence(10.39) is None and s.silence(10.41) == pytest.approx(0.41)
    s.released_at = 11.0
    assert s.stale_press(11.3) and not s.stale_press(11.5)
    off = Supervision(False, 0.4)
    assert not off.waiting and off.silence(1e9) is None
    assert heartbeat_refusal("launcher") is None and "only the launcher" in heartbeat_refusal("h0")


class _Sample:
    def __init__(self, payload: bytes) -> None:
        self.payload = type("P", (), {"to_bytes": lambda _self: payload})()


def test_human_estop_repeated_until_every_recent_actor_confirms(monkeypatch):
    """A client's press goes out again every REPEAT_S until each actor heard recently says, after the press, that it is
    held by the e-stop."""
    from khgrl.common.wire.messages import ActorInfo, Status
    from khgrl.human_bridge import estop

    monkeypatch.setattr(estop, "REPEAT_S", 0.0)
    sent = []
    press = estop.EStopPress(lambda: sent.append(1))

    def status(actor: str, held: str) -> _Sample:
        info = ActorInfo(id=actor, episode=1, t=0, transitions=0, sent=0, next_seq=0, outbox=0, received=0, durable=0,
                         trained=0, weights_version=0, ack_version=0, learner_alive=True, waits=0, wait_s=0.0,
                         resends=0, corrections={}, intervening=False, rejects={}, paused=False, period_ms_p50=None,
                         held=held)
        return _Sample(encode(Status(role="actor", info=info), actor, 0))

    press.on_status(status("a0", ""))
    press.on_status(status("a1", ""))
    press.press()
    press.tick()
    press.on_status(status("a0", "e-stop by human client h9"))
    press.tick()
    assert press.since is not None and len(sent) == 3  # a1 has not confirmed
    time.sleep(0.001)
    press.on_status(status("a1", "e-stop by the watchdog (no heartbeat from the supervisor for 0.41 s)"))
    press.tick()
    assert press.since is None and press.confirmed_after is not None and len(sent) == 3


def test_khgrl_stop_loads_nothing_heavy_before_its_message():
    """``khgrl stop --now``'s path to its first message (the ``khgrl`` command, ``khgrl stop``, the session) loads no
    numpy, no settings module and no wire-protocol module (defect 7: keystroke to held). Before: the command imported
    the passage scenarios (numpy) and ``khgrl stop`` the protocol and the settings before it connected."""
    import subprocess
    import sys

    heavy = ("numpy", "khgrl.common.config.settings", "khgrl.common.wire.protocol", "khgrl.common.wire.messages")
    code = ("import sys, khgrl.deploy.cli, khgrl.deploy.run.stop, khgrl.common.delivery.transport, "
            f"khgrl.common.delivery.declare; print([m for m in {heavy!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
