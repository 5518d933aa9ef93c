"""``khgrl bench vouch``: what vouching for human data costs (``common/delivery/vouching.py``), per row.

- the human client: signing one correction (:func:`~khgrl.common.delivery.vouching.sign_correction`);
- the actor: the evidence of one row (:func:`~khgrl.common.delivery.vouching.evidence`) and the bytes it adds to a
  batch on the wire;
- the learner: :meth:`~khgrl.common.delivery.vouching.Vouching.judge` of a batch of ``rows`` intervened rows, each
  with its own signed correction (one Ed25519 verification a row, the worst case: lock-step), with one correction
  held over the whole batch (one verification), and without evidence (the rows refused as unvouched), per row;
  and the same batch's decode, for scale.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["run_vouch_benchmark"]


def _per_row(fn, repeats: int, rows: int) -> np.ndarray:
    """``fn()`` timed ``repeats`` times, each as µs per row."""
    out = np.empty(repeats)
    for i in range(repeats):
        t = time.perf_counter()
        fn()
        out[i] = (time.perf_counter() - t) * 1e6 / rows
    return out


def _batch(rows: int, vouch) -> object:
    from khgrl.common.wire.messages import Transitions

    rng = np.random.default_rng(0)
    obs = rng.uniform(0, 1, (rows, 10)).astype(np.float32)
    return Transitions(actor="a0", first_step=10_000, obs=obs, next_obs=obs, reward=np.zeros(rows, np.float32),
                       action=rng.uniform(-1, 1, (rows, 2)).astype(np.float32), terminated=np.zeros(rows, np.uint8),
                       truncated=np.zeros(rows, np.uint8), intervened=np.ones(rows, np.uint8),
                       clipped=np.zeros(rows, np.uint8), base_seq=0, stream="s", task="0123456789abcdef", vouch=vouch)


def run_vouch_benchmark(rows: int = 256, repeats: int = 20, out: str | None = None) -> dict:
    """Time signing, evidence and the learner's check for batches of ``rows`` intervened rows; print and return.

    :param rows: intervened rows per batch.
    :param repeats: timed batches per case (median and p99 of the per-row cost reported).
    :param out: also write the results as JSON here.
    """
    from khgrl.common.delivery.role_keys import PublicKeys, load_private, make_run_keys
    from khgrl.common.delivery.vouching import Vouching, evidence, sign_correction
    from khgrl.common.wire.messages import Correction, Transitions
    from khgrl.common.wire.protocol import decode, encode

    if rows < 1 or repeats < 1:
        raise ValueError("--rows and --repeats must be >= 1")
    with tempfile.TemporaryDirectory() as tmp:
        make_run_keys(tmp, [("actor", "a0"), ("human", "gui")], fresh=True)
        key = load_private(tmp, "human:gui")
        base = Correction(client="gui", actor="a0", active=True, p_h=np.array([0.3, -0.2]), episode=5, t=10)
        words = [decode(Correction, encode(sign_correction(base.replace(step=i), key, i), "gui", i))
                 for i in range(rows)]
        sign = _per_row(lambda: [sign_correction(base, key, i) for i in range(rows)], repeats, rows)
        ev = _per_row(lambda: [evidence(i, w) for i, w in enumerate(words)], repeats, rows)
        each = tuple(evidence(i, w) for i, w in enumerate(words))
        held = tuple(evidence(i, words[0]) for i in range(rows))
        payload = {name: encode(_batch(rows, v), "a0", 0) for name, v in (("each", each), ("none", None))}
        msgs = {name: decode(Transitions, p) for name, p in payload.items()}
        held_msg = decode(Transitions, encode(_batch(rows, held), "a0", 0))
        public = PublicKeys(tmp)
        res = {"sign_us": sign, "evidence_us": ev,
               "judge_each_row_signed_us": _per_row(lambda: Vouching(public).judge(msgs["each"]), repeats, rows),
               "judge_one_held_word_us": _per_row(lambda: Vouching(public).judge(held_msg), repeats, rows),
               "judge_no_evidence_us": _per_row(lambda: Vouching(public).judge(msgs["none"]), repeats, rows),
               "decode_batch_us": _per_row(lambda: decode(Transitions, payload["each"]), repeats, rows)}
        vouched = Vouching(public).judge(msgs["each"]).vouched
    summary = {k: {"median": float(np.median(v)), "p99": float(np.percentile(v, 99))} for k, v in res.items()}
    summary["wire_bytes_per_row"] = (len(payload["each"]) - len(payload["none"])) / rows
    summary["rows"], summary["vouched"] = rows, vouched
    for k, v in res.items():
        print(f"{k:26s} median {np.median(v):8.2f} us/row   p99 {np.percentile(v, 99):8.2f} us/row")
    print(f"evidence on the wire: {summary['wire_bytes_per_row']:.1f} B per intervened row; {vouched} of {rows} "
          f"rows vouched for")
    if out:
        Path(out).write_text(json.dumps(summary, indent=1))
    return summary
