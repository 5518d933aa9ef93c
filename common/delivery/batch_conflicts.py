"""Two different batches signed by one actor for the same (stream, seq): a split brain, not a re-send
(docs/protocol.md, "Trust model").

With role keys only the holder of ``actor:X``'s private key can sign a batch of actor X, so a second batch for a
(stream, seq) already taken, validly signed but with other contents, means that two processes sign as X (a copied
key, a second actor process on another machine, a certificate holder who also has the key). The learner keeps the
first batch -- the data already stored is never replaced -- refuses the second (counted as ``conflict``), and raises
the split-brain alarm: a line in its status (``alarm``), which ``khgrl up`` makes the run's error, as for an actor's
alarm. A re-send of the same batch re-stamped with a newer ``base_seq`` is not a conflict: the fingerprint leaves
``base_seq`` out.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

from khgrl.common.delivery import run_key

__all__ = ["SignedSeqs", "KEEP_PER_STREAM"]

KEEP_PER_STREAM = 4096  # the newest batches of a stream whose fingerprints are kept (64 KiB per stream)
_FINGERPRINT_KEY = b"khgrl-batch-fingerprint".ljust(32, b"\0")  # public: only separates this digest from others
_FP_BYTES = 16


def fingerprint(msg: Any) -> bytes:
    """A digest of a received batch's contents and number, ``base_seq`` (re-stamped on re-sends) and the
    signature fields left out.

    :param msg: a decoded :class:`~khgrl.common.wire.messages.Transitions`.
    """
    return run_key.batch_mac(msg.replace(base_seq=None), _FINGERPRINT_KEY, msg.envelope.seq)[:_FP_BYTES]


class SignedSeqs:
    """The fingerprints of the validly signed batches taken, per (actor, stream): :meth:`conflict` says when a
    second, different one comes for the same seq.

    :param keep: fingerprints kept per stream (the oldest are forgotten).
    """

    def __init__(self, keep: int = KEEP_PER_STREAM) -> None:
        self.keep = keep
        self.seen: dict[tuple[str, str | None], OrderedDict[int, bytes]] = {}
        self.conflicts = 0
        self.alarm = ""  # the first conflict, in one line ("" while none)

    def conflict(self, msg: Any) -> str | None:
        """Why ``msg`` (a validly signed batch) conflicts with one taken before (None: it does not; it is noted).

        :param msg: the decoded batch.
        """
        seq, fp = msg.envelope.seq, fingerprint(msg)
        table = self.seen.setdefault((msg.actor, msg.stream), OrderedDict())
        first = table.get(seq)
        if first is None:
            table[seq] = fp
            while len(table) > self.keep:
                table.popitem(last=False)
            return None
        if first == fp:
            return None
        self.conflicts += 1
        why = (f"split brain: two different batches signed by {msg.signer or 'actor:' + msg.actor} for stream "
               f"{msg.stream} seq {seq}: the first is kept, this one refused (two processes hold actor {msg.actor}'s "
               f"key)")
        if not self.alarm:
            self.alarm = why
        return why
