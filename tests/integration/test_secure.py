"""``khgrl up --secure``: every attack of issue 14 is rejected while the run completes exactly as without
``--secure``.

The same seeded run twice, plain and secure. During the secure one, this test process attacks it from sessions
with no certificate (refused at the TLS handshake: nothing can be sent) and with the certificates of other roles
made for the run (``monitor``, ``human-user``; ``actor-a0`` for the keys that are not an actor's): forged weights
with version 10**9, transitions from a made-up actor id and under the real actor's key, a forged ack that would
make the actor drop batches no checkpoint holds, a spoofed release and a forged correction of the scripted
human's intervention, ``control/all stop``, and the e-stop (``control/all estop`` and a human's
``human/scripted/request estop`` from the certificates that may not send them). The attack runs while the
launcher's e-stop holds the actor (``khgrl stop RUN_DIR --now`` with the run's launcher certificate, then
``--release``), so the run cannot end under it. An observer session (the run's ``monitor`` certificate) records
every message the router delivers: none of the forged ones may arrive. Then the run must end on its own (exit 0,
not stopped), hold no transition of the made-up actor, lose and duplicate nothing, and give the same episodes.csv
as the plain run (every column but wall time).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from helpers import read_json, untimed
from launch import FAST, UP, Launcher, _env, _rows, _run

pytestmark = pytest.mark.integration

ARGS = [*FAST, "--episodes", "2", "--human-episodes", "2", "--seed", "11"]


def _khgrl(*args: str):
    import subprocess

    return subprocess.run([*UP[:-1], *args], env=_env(), capture_output=True, text=True, timeout=60)


def _session(run_dir, cn: str, endpoint: str):
    from khgrl.common.delivery.transport import _open
    from khgrl.common.delivery.zenoh_config import build_config

    conf = build_config("client", [], [endpoint], 3000, run_dir / "certs" / "zenoh" / f"{cn}.json5")
    return _open(conf, lambda: False, 20, cn)


def _forgeries(keys, weights_payload: bytes) -> list[tuple[str, str, bytes]]:
    """(attack, key, payload) of every forged message: each well-formed, so that only the router can stop it."""
    from khgrl.benchmarks.ingest_many import _as_actor
    from khgrl.benchmarks.runtime.link import batches
    from khgrl.common.wire.messages import Ack, Control, Correction, Weights
    from khgrl.common.wire.protocol import decode, encode

    real = decode(Weights, weights_payload)
    forged_w = encode(real.replace(version=10**9, tensors={k: np.zeros_like(v) for k, v in real.tensors.items()}),
                      "learner", 10**6)
    out = [("forged weights, version 10**9", keys.weights, forged_w)]
    for actor, what in (("evil", "transitions from a made-up actor id"), ("a0", "transitions under a0's key")):
        out += [(what, keys.transitions(actor), _as_actor(p, actor, decode, encode)) for p in batches(64, 32, seed=1)]
    out.append(("forged ack", keys.ack("a0"), encode(Ack(actor="a0", received=10**6, durable=10**6, trained=0,
                                                         version=0, epoch=real.epoch or "e"), "learner", 10**6)))
    out.append(("spoofed release", keys.correction("scripted"),
                encode(Correction(client="scripted", actor="a0", active=False), "scripted", 10**6)))
    out.append(("forged correction", keys.correction("scripted"), encode(
        Correction(client="scripted", actor="a0", active=True, p_h=np.array([0.99, 0.99])), "scripted", 10**6 + 1)))
    out.append(("control/all stop", keys.control("all"), encode(Control(command="stop"), "launcher", 10**6)))
    out.append(("control/all estop", keys.control("all"), encode(Control(command="estop"), "launcher", 10**6 + 1)))
    out.append(("a human's e-stop", keys.human_request("scripted"), encode(Control(command="estop"), "scripted", 9)))
    return out


def _attack(up: Launcher, runtime: dict) -> tuple[list[tuple[str, bytes]], list[bytes]]:
    """Every forgery from every attacking identity; returns ((attacker: attack, payload) sent, what the observer
    received)."""
    import zenoh
    from khgrl.common.delivery.transport import _open
    from khgrl.common.delivery.zenoh_config import build_config
    from khgrl.common.wire.protocol import Keys

    keys, ep = Keys(runtime["run"]), runtime["endpoint"]
    plain = build_config("client", [], [ep.replace("tls/", "tcp/")], 3000)
    plain.insert_json5("connect/timeout_ms", "0")
    plain.insert_json5("connect/exit_on_failure", "true")
    with pytest.raises(ConnectionError):  # no certificate: refused before anything can be sent
        _open(plain, lambda: False, 10, "attacker without a certificate").close()
    seen: list[bytes] = []
    observer = _session(up.run_dir, "monitor", ep)
    sub = observer.declare_subscriber(f"khgrl/{runtime['run']}/**", lambda s: seen.append(s.payload.to_bytes()),
                                      allowed_origin=zenoh.Locality.REMOTE)
    attackers = [_session(up.run_dir, cn, ep) for cn in ("monitor", "human-user", "actor-a0")]
    sent: list[tuple[str, bytes]] = []
    try:
        weights = [r.ok.payload.to_bytes() for r in observer.get(keys.weights, timeout=5.0) if r.ok]
        assert weights, "a monitor may query the weights"
        for s, cn in zip(attackers, ("monitor", "human-user", "actor-a0")):
            for attack, key, payload in _forgeries(keys, weights[0]):
                if cn == "actor-a0" and key == keys.transitions("a0"):
                    continue  # the actor's own certificate may publish its own stream: that is its key
                s.put(key, payload)
                sent.append((f"{cn}: {attack}", payload))
        time.sleep(3.0)
    finally:
        sub.undeclare()
        for s in (*attackers, observer):
            s.close()
    return sent, seen


@pytest.mark.timeout(900)
def test_secure_run_rejects_every_attack_and_repeats_the_plain_run(tmp_path):
    plain = _run(tmp_path / "plain", *ARGS, timeout=400)
    assert plain.returncode == 0, f"plain run exited {plain.returncode}\n{plain.stdout}\n{plain.stderr}"
    up = Launcher(tmp_path, tmp_path / "secure", *ARGS, "--secure")
    try:
        up.wait_line("[a0] episode 1:", 300)
        runtime = read_json(up.run_dir / "config.json")["runtime"]
        assert runtime["endpoint"].startswith("tls/127.0.0.1:") and runtime["secure"] is True
        estop = _khgrl("stop", str(up.run_dir), "--now")  # the launcher's certificate may press the e-stop
        assert estop.returncode == 0 and "a0: held by the e-stop" in estop.stdout, estop.stdout + estop.stderr
        sent, seen = _attack(up, runtime)
        release = _khgrl("stop", str(up.run_dir), "--release")
        assert release.returncode == 0 and "a0: released" in release.stdout, release.stdout + release.stderr
        delivered = set(seen)
        through = sorted({attack for attack, payload in sent if payload in delivered})
        assert not through, f"forged messages got through the router: {through}"
        assert seen, "the observer received the run's own messages"
        rc = up.proc.wait(timeout=400)
        assert rc == 0, f"secure run exited {rc}\n{up.stdout}\n{up.stderr}"
    finally:
        up.cleanup()
    summary = read_json(up.run_dir / "summary.json")
    assert summary["stopped_by"] is None and not summary["failed"]
    assert summary["a0"].get("refused_acks", 0) == 0, "the forged ack reached the actor"
    assert summary["a0"]["weights"]["final_version"] < 10**6 and not summary["a0"]["rejects"], summary["a0"]
    safety = read_json(up.run_dir / "actor-a0" / "summary.json")["safety"]
    assert [e["by"] for e in safety["estop_events"]] == ["launcher"], safety  # no forged e-stop reached the actor
    state = read_json(up.run_dir / "learner" / "checkpoint" / "state.json")
    assert set(state["actors"]) == {"a0"}, f"the learner admitted {sorted(state['actors'])}"
    from khgrl.benchmarks.scale import provenance_check

    acct = provenance_check(up.run_dir)
    assert acct["lost"] == 0 and acct["duplicated"] == 0 and acct["produced"] > 0, acct
    assert untimed(_rows(up.run_dir)) == untimed(_rows(tmp_path / "plain")), "the secure run gave other episodes"
    for name, cn in (("learner", "learner"), ("a0", "actor-a0"), ("human-scripted", "human-scripted")):
        log = (up.run_dir / "logs" / f"{name}.log").read_text()
        assert f"identity: {cn} (mutual TLS)" in log, f"{name}'s log does not say who it runs as"
    assert "(access control on)" in (up.run_dir / "logs" / "router.log").read_text()
