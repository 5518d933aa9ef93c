"""The signing key per role (common/delivery/role_keys.py) and signed control (common/delivery/control_auth.py):
who may press, release, stop and confirm ready; replays refused."""

from __future__ import annotations

import time

import pytest
from khgrl.common.delivery.control_auth import OPERATOR, ControlGate, ControlSigner, operator_side
from khgrl.common.delivery.role_keys import (
    PublicKeys,
    RoleKeyError,
    key_id,
    load_private,
    make_keys,
    make_run_keys,
    private_path,
    role_of,
)
from khgrl.common.wire.messages import Control
from khgrl.common.wire.protocol import LAUNCHER, Keys, ProtocolError, decode, encode

KEYS = Keys("r1")


def _run(tmp_path):
    make_run_keys(tmp_path, [("learner", "learner"), ("actor", "a0"), ("human", "h0")], fresh=True)
    return tmp_path


def _got(payload: bytes) -> Control:
    return decode(Control, payload)


def test_each_process_gets_its_own_0600_private_key_and_everyone_the_public_table(tmp_path):
    run = _run(tmp_path)
    table = PublicKeys.read_table(run)
    assert sorted(table) == ["actor:a0", "human:h0", "human:user", "learner:learner", OPERATOR]  # (+ the spare)
    for kid in table:
        path = private_path(run, kid)
        assert path.stat().st_mode & 0o777 == 0o600 and path.stat().st_size == 32
    assert (run / "keys" / "public.json").stat().st_mode & 0o077 == 0o044  # public: readable
    again = make_keys(run, ["actor:a0", "actor:a1"])  # an existing key is kept, a new id gets one
    assert again == ["actor:a1"] and PublicKeys.read_table(run)["actor:a0"] == table["actor:a0"]
    assert make_keys(run, ["actor:a0"], fresh=True) == ["actor:a0"]
    assert PublicKeys.read_table(run)["actor:a0"] != table["actor:a0"]
    assert role_of("human:h0") == "human" and role_of("boss:x") == "" and role_of("nocolon") == ""
    for role, ident in (("boss", "x"), ("actor", "a/b"), ("actor", "a:b"), ("actor", "")):
        with pytest.raises(RoleKeyError):
            key_id(role, ident)


def test_a_private_key_file_is_checked_and_a_missing_one_means_unsigned(tmp_path):
    run = _run(tmp_path)
    assert load_private(run, "actor:a9") is None and load_private(None, OPERATOR) is None
    assert load_private(run, OPERATOR) is not None
    bad = tmp_path / "bad.key"
    bad.write_bytes(b"x" * 31)
    with pytest.raises(RoleKeyError, match="31 bytes"):
        load_private(None, OPERATOR, bad)
    with pytest.raises(RoleKeyError):
        load_private(None, OPERATOR, tmp_path / "nope.key")
    (run / "keys" / "public.json").write_text("{not json")
    with pytest.raises(RoleKeyError, match="not a key table"):
        PublicKeys(run)


def test_only_the_operator_sends_control_and_only_a_client_its_own_requests(tmp_path):
    run = _run(tmp_path)
    gate = ControlGate.of_run(run)
    operator, _ = operator_side(run)
    actor = ControlSigner.load(run, "actor:a0")
    human = ControlSigner.load(run, "human:h0")
    for target in ("actor", "a0", "all", "learner"):
        for command in ("estop", "release", "stop", "ready", "pause"):
            key = KEYS.control(target)
            assert gate.check(_got(operator.payload(key, command, LAUNCHER, 0)), key) is None
            assert "only the operator" in gate.check(_got(actor.payload(key, command, LAUNCHER, 0)), key)
            assert "only the operator" in gate.check(_got(human.payload(key, command, LAUNCHER, 0)), key)
    own, other = KEYS.human_request("h0"), KEYS.human_request("h1")
    assert gate.check(_got(human.payload(own, "estop", "h0", 0)), own) is None
    assert "only human client 'h1'" in gate.check(_got(human.payload(other, "estop", "h1", 1)), other)
    assert "only human client" in gate.check(_got(operator.payload(own, "estop", "h0", 2)), own)
    unsigned = _got(encode(Control(command="release"), LAUNCHER, 7))
    assert "not signed" in gate.check(unsigned, KEYS.control("a0"))
    assert "not a control key" in gate.check(_got(operator.payload(KEYS.weights, "stop", LAUNCHER, 9)), KEYS.weights)


def test_a_forged_moved_or_replayed_signature_is_refused(tmp_path):
    run = _run(tmp_path)
    gate = ControlGate.of_run(run)
    operator, _ = operator_side(run)
    key = KEYS.control("actor")
    release = operator.payload(key, "release", LAUNCHER, 3)
    assert "wrong signature" in gate.check(_got(release), KEYS.control("a0"))  # signed for another key
    assert "wrong signature" in gate.check(_got(release), Keys("r2").control("actor"))  # another run
    m = _got(release)
    assert "wrong signature" in gate.check(m.replace(command="stop"), key)  # a changed command
    assert gate.check(_got(release), key) is None
    assert "a replay" in gate.check(_got(release), key)  # the same message again
    old = _got(operator.payload(key, "release", LAUNCHER, 9))
    object.__setattr__(old, "envelope", old.envelope.__class__("control", LAUNCHER, 9, time.time() - 60))
    assert "outside the 10 s window" in gate.check(old, key)
    stranger = ControlSigner.load(None, "human:h7", private_path(run, "human:h0"))  # a key the run does not know
    msg = _got(stranger.payload(KEYS.human_request("h7"), "estop", "h7", 0))
    assert "does not know" in gate.check(msg, KEYS.human_request("h7"))
    public = run / "keys" / "public.json"
    good = public.read_text()
    public.write_text("{damaged")  # a damaged table while the run goes on: refused with the reason, no exception
    assert "not a key table" in gate.check(msg, KEYS.human_request("h7"))
    assert gate.check(_got(operator.payload(key, "stop", LAUNCHER, 20)), key) is None  # the known keys stay
    public.write_text(good)
    make_keys(run, ["human:h7"])  # a client added while the run goes on: known at its next message
    h7 = ControlSigner.load(run, "human:h7")
    assert gate.check(_got(h7.payload(KEYS.human_request("h7"), "estop", "h7", 1)), KEYS.human_request("h7")) is None


def test_two_operator_processes_messages_taken_in_either_order(tmp_path):
    """The launcher's heartbeat and ``khgrl stop`` sign with the one operator key; the router may deliver the newer
    first. Both are taken (a "newer than the last" rule refused the older one: a press lost to a heartbeat)."""
    run = _run(tmp_path)
    gate = ControlGate.of_run(run)
    operator, _ = operator_side(run)
    key = KEYS.control("actor")
    press = operator.payload(key, "estop", LAUNCHER, 0)
    time.sleep(0.01)
    beat = operator.payload(key, "heartbeat", LAUNCHER, 41)
    assert gate.check(_got(beat), key) is None and gate.check(_got(press), key) is None
    assert "a replay" in gate.check(_got(press), key)


def test_without_role_keys_nothing_is_checked_and_nothing_signed(tmp_path):
    gate = ControlGate.of_run(tmp_path)
    assert not gate.active
    assert gate.check(_got(encode(Control(command="release"), "anyone", 0)), KEYS.control("a0")) is None
    unsigned = ControlSigner.load(tmp_path, OPERATOR)  # no key file: unsigned, as before
    assert unsigned.key is None and _got(unsigned.payload(KEYS.control("a0"), "stop", LAUNCHER, 0)).sig is None


def test_a_signature_field_of_the_wrong_size_is_refused():
    import msgpack

    body = {"v": 1, "kind": "control", "sender": LAUNCHER, "seq": 0, "ts": time.time(), "command": "release",
            "signer": OPERATOR, "sig": b"x" * 63}
    with pytest.raises(ProtocolError, match="sig: 63 bytes"):
        decode(Control, msgpack.packb(body, use_bin_type=True))
    body["sig"], body["signer"] = b"x" * 64, "a/b"
    with pytest.raises(ProtocolError, match="bad identifier"):
        decode(Control, msgpack.packb(body, use_bin_type=True))
