"""A key per role for data (issue 34, point 4; point 3, an actor's key that makes no weights or acks anyone takes,
is attack (d) of test_attack_split.py's plain-mode run). Real processes; each attacker holds exactly the credentials
named (the run's key, a certificate, one role's private key) and signs as a real process of that role would.

* ``--secure`` with a0's certificate (not a0's role key) and the run's key: (b) batches on a0's stream with a0's
  stream id and the next seqs, with the right ``mac``. The learner refuses each (``sig`` rejects), stores none, and
  a0 runs on undisturbed. (Before, against main: the learner stored the forged batches as a0's; a0 saw acks up to
  seq 12 when it had sent 10 and exited 4, and the run ended with "another process publishes as actor a0".)
  (c) Then with a copy of a0's role key (two processes sign as a0): a different batch for a (stream, seq) the
  learner already acked. The learner keeps the first, refuses this one (``conflict``) and raises the split-brain
  alarm in its status; ``khgrl up`` ends the run with that line (exit 1). (Before: main never gets here, (b) ended
  its run; by its code a second batch for a received seq is dropped as a duplicate without a word.)
"""

from __future__ import annotations

import subprocess
import threading
import time

import numpy as np
import pytest

from helpers import read_json, wait_for
from launch import KGRL, Launcher

pytestmark = pytest.mark.integration


def _session(run_dir, cn: str, endpoint: str):
    from khgrl.common.delivery.transport import _open
    from khgrl.common.delivery.zenoh_config import build_config

    conf = build_config("client", [], [endpoint], 3000, run_dir / "certs" / "zenoh" / f"{cn}.json5")
    return _open(conf, lambda: False, 20, cn)


def _holder(run_dir, kid: str | None):
    """What the attacker signs with: the run's key and (``kid``) that role's private key, as that process would."""
    from khgrl.common.delivery import run_key
    from khgrl.common.delivery.data_keys import DataKeys
    from khgrl.common.delivery.role_keys import load_private

    return DataKeys(run=run_key.load(run_dir), kid=kid or "", private=load_private(run_dir, kid) if kid else None)


def _sign(msg, holder, seq: int | None = None):
    from khgrl.common.delivery import data_keys

    return data_keys.sign(msg, holder) if seq is None else data_keys.sign_batch(msg, holder, seq)


def _unsigned(msg) -> dict:
    """The fields that make ``msg`` a message to be signed anew (its envelope, ``mac``, ``signer``, ``sig``)."""
    return {f: None for f in ("envelope", "mac", "signer", "sig") if hasattr(msg, f)}


FORGE_FROM = 10  # KGRL's learning_starts 64 = 8 batches of 8


def _ended(up: Launcher, timeout: float) -> int:
    try:
        return up.proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"khgrl up did not end {timeout:.0f} s after the attack\n{up.stdout[-3000:]}") from None


class _Watch:
    """a0's batches and acks and the learner's status, as a monitor sees them."""

    def __init__(self, session, keys) -> None:
        from khgrl.common.wire.messages import Ack, Status, Transitions
        from khgrl.common.wire.protocol import decode

        self.lock = threading.Lock()
        self.batch, self.acked, self.learner = None, -1, None

        def on_batch(sample) -> None:
            msg = decode(Transitions, sample.payload.to_bytes())
            with self.lock:
                if self.batch is None or msg.envelope.seq >= self.batch.envelope.seq:
                    self.batch = msg

        def on_ack(sample) -> None:
            msg = decode(Ack, sample.payload.to_bytes())
            with self.lock:
                self.acked = max(self.acked, msg.received)

        def on_status(sample) -> None:
            msg = decode(Status, sample.payload.to_bytes())
            if msg.role == "learner":
                self.learner = msg.info

        self.subs = [session.declare_subscriber(keys.transitions("a0"), on_batch),
                     session.declare_subscriber(keys.ack("a0"), on_ack),
                     session.declare_subscriber(keys.status("learner", "*"), on_status)]


@pytest.mark.timeout(600)
def test_secure_a0_certificate_without_its_key_forges_nothing_a_second_signer_raises_split_brain(tmp_path):
    from khgrl.common.wire.protocol import Keys, encode

    up = Launcher(tmp_path, tmp_path / "sec", *KGRL, "--secure", "--episodes", "40", "--seed", "5",
                  "--timeout", "400")
    up.wait_line("khgrl up: run ", 120)
    runtime = read_json(up.run_dir / "config.json")["runtime"]
    keys, ep = Keys(runtime["run"]), runtime["endpoint"]
    try:
        watcher = _session(up.run_dir, "monitor", ep)
        attacker = _session(up.run_dir, "actor-a0", ep)
        watch = _Watch(watcher, keys)
        try:
            wait_for(lambda: watch.batch is not None and watch.batch.envelope.seq >= FORGE_FROM, 180,
                     "a0 past learning_starts")
            # (b) a0's certificate and the run's key, not a0's role key: the next seqs, reward 100
            cert_only = _holder(up.run_dir, None)
            sent_b = []
            for _ in range(3):
                with watch.lock:
                    msg = watch.batch
                seq = msg.envelope.seq + 1
                forged = msg.replace(first_step=msg.first_step + msg.n, reward=np.full(msg.n, 100.0, np.float32),
                                     **_unsigned(msg))
                attacker.put(keys.transitions("a0"), encode(_sign(forged, cert_only, seq), "a0", seq))
                sent_b.append(seq)
                time.sleep(2.0)
            time.sleep(3.0)
            assert up.proc.poll() is None, f"the run ended after (b)\n{up.stderr[-3000:]}"
            info_b = watch.learner
            assert info_b is not None and info_b.rejects.get("sig", 0) >= 3, info_b
            assert info_b.alarm == "", info_b.alarm
            # (c) a copy of a0's role key: a different batch for a seq the learner acked
            copy = _holder(up.run_dir, "actor:a0")
            with watch.lock:
                msg, acked = watch.batch, watch.acked
            assert acked >= FORGE_FROM, acked
            # stamped as a0 would stamp it at that seq (the newest batch seen may already be past it)
            again = msg.replace(reward=np.full(msg.n, 100.0, np.float32), base_seq=min(msg.base_seq or 0, acked),
                                **_unsigned(msg))
            t0 = time.monotonic()
            attacker.put(keys.transitions("a0"), encode(_sign(again, copy, acked), "a0", acked))
            rc = _ended(up, 60)
            ended = time.monotonic() - t0
        finally:
            for sub in watch.subs:
                sub.undeclare()
            attacker.close()
            watcher.close()
    finally:
        up.cleanup()
    print(f"secure, a0's certificate: forged batches {sent_b} refused, learner rejects {info_b.rejects}; a second "
          f"signer at seq {acked}: khgrl up exited {rc} {ended:.1f} s later")
    assert rc == 1, f"khgrl up exited {rc}\n{up.stdout[-2000:]}\n{up.stderr[-2000:]}"
    assert "khgrl up: error: learner learner: split brain" in up.stderr, up.stderr[-3000:]
    summary = read_json(up.run_dir / "summary.json")
    assert f"seq {acked}" in summary["error"] and "actor:a0" in summary["error"], summary["error"]
    a0_log = (up.run_dir / "actor-a0" / "actor.log").read_text()
    assert "another process publishes as actor a0" not in a0_log  # (b) stored nothing as a0's
    assert "split brain" in (up.run_dir / "learner" / "learner.log").read_text()
