"""``khgrl bench control``: what signed control costs (``common/delivery/control_auth.py``).

- the receiver (the actor, between two steps): decoding a ``control`` message alone, and decoding plus
  :meth:`~khgrl.common.delivery.control_auth.ControlGate.check` -- a genuine operator-signed message (the Ed25519
  verification), an unsigned one and one with a wrong signature (refused) -- median and p99 per message;
- the sender (``khgrl stop --now``, the launcher, a human client): :meth:`ControlSigner.payload` per message, and in a
  fresh interpreter the extra import of the signing module and the load of the operator's key file (what the
  keystroke-to-held path pays once).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["run_control_benchmark"]

_IMPORT = """
import time
t0 = time.perf_counter()
import khgrl.common.wire.protocol
t1 = time.perf_counter()
from khgrl.common.delivery.control_auth import OPERATOR, ControlSigner
t2 = time.perf_counter()
signer = ControlSigner.load({run!r}, OPERATOR)
signer.payload("khgrl/r/control/actor", "estop", "launcher", 0)
t3 = time.perf_counter()
print((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3)
"""


def _times(fn, n: int) -> np.ndarray:
    """``fn(i)`` for i < n, each timed (µs)."""
    out = np.empty(n)
    for i in range(n):
        t = time.perf_counter()
        fn(i)
        out[i] = (time.perf_counter() - t) * 1e6
    return out


def run_control_benchmark(messages: int = 2000, out: str | None = None) -> dict:
    """Time the receiver's checks and the sender's signing of ``messages`` control messages each; print and return.

    :param messages: messages per case.
    :param out: also write the results as JSON here.
    """
    from khgrl.common.delivery.control_auth import OPERATOR, ControlGate, ControlSigner
    from khgrl.common.delivery.role_keys import make_run_keys
    from khgrl.common.wire.messages import Control
    from khgrl.common.wire.protocol import LAUNCHER, Keys, decode, encode

    if messages < 1:
        raise ValueError("--messages must be >= 1")
    with tempfile.TemporaryDirectory() as tmp:
        make_run_keys(tmp, [("actor", "a0")], fresh=True)
        signer, key = ControlSigner.load(tmp, OPERATOR), Keys("bench").control("actor")
        signed = [signer.payload(key, "estop" if i % 2 else "release", LAUNCHER, i) for i in range(messages)]
        unsigned = encode(Control(command="release"), LAUNCHER, 0)
        forged = ControlSigner.load(tmp, "actor:a0")
        forged.kid = OPERATOR  # a0's key claiming to be the operator's: a wrong signature
        wrong = [forged.payload(key, "release", LAUNCHER, i) for i in range(messages)]
        gate = ControlGate.of_run(tmp)
        res = {"decode_us": _times(lambda i: decode(Control, signed[i]), messages),
               "decode_verify_us": _times(lambda i: gate.check(decode(Control, signed[i]), key), messages),
               "unsigned_refused_us": _times(lambda i: gate.check(decode(Control, unsigned), key), messages),
               "wrong_signature_refused_us": _times(lambda i: gate.check(decode(Control, wrong[i]), key), messages),
               "sign_us": _times(lambda i: signer.payload(key, "estop", LAUNCHER, i), messages)}
        taken = sum(gate.check(decode(Control, p), key) is None for p in signed)  # (all taken before: replays now)
        fresh = subprocess.run([sys.executable, "-c", _IMPORT.format(run=tmp)], capture_output=True, text=True,
                               check=True).stdout.split()
    summary = {k: {"median": float(np.median(v)), "p99": float(np.percentile(v, 99))} for k, v in res.items()}
    summary["replays_taken"] = taken
    summary["stop_path_ms"] = dict(zip(("protocol_import", "signing_import", "key_load_and_first_sign"),
                                       map(float, fresh)))
    for k, v in res.items():
        print(f"{k:28s} median {np.median(v):8.1f} us   p99 {np.percentile(v, 99):8.1f} us   ({len(v)} messages)")
    p = summary["stop_path_ms"]
    print(f"khgrl stop's path, once: protocol import {p['protocol_import']:.1f} ms, signing module import "
          f"{p['signing_import']:.1f} ms, key load + first signature {p['key_load_and_first_sign']:.2f} ms")
    print(f"the actor's verification per control message: median {summary['decode_verify_us']['median'] / 1e3:.3f} ms "
          f"(decode alone {summary['decode_us']['median'] / 1e3:.3f} ms); replays of the {messages} taken: {taken}")
    if out:
        Path(out).write_text(json.dumps(summary, indent=1))
    return summary
