"""The signing side of signed control (:mod:`khgrl.common.delivery.control_auth` checks it): the operator's and the
human clients' :class:`ControlSigner`, built without numpy so that ``khgrl stop --now`` starts fast (the payload is
:func:`khgrl.common.wire.control.control_payload`, byte for byte what ``encode`` makes of a signed ``Control``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from khgrl.common.delivery.role_keys import key_id, load_private
from khgrl.common.wire.control import control_payload

__all__ = ["OPERATOR", "signed_bytes", "ControlSigner"]

OPERATOR = key_id("operator", "launcher")  # the launcher's and the operator's khgrl stop / khgrl ready


def signed_bytes(key_expr: str, command: str, sender: str, seq: int, ts: float, signer: str) -> bytes:
    """What a control signature covers (canonical JSON: ids are key chunks, ``ts`` a float64's repr).

    :param key_expr: the key it is published on.
    :param command: the command.
    :param sender: the envelope's sender.
    :param seq: the envelope's seq.
    :param ts: the envelope's ts.
    :param signer: the signer's key id.
    """
    return json.dumps(["khgrl-control", key_expr, command, sender, int(seq), float(ts), signer],
                      separators=(",", ":"), ensure_ascii=True).encode()


class ControlSigner:
    """Makes the control payloads of one signer (or unsigned ones without a key: a run without role keys).

    :param key: the signer's private key (None: unsigned).
    :param kid: its key id.
    """

    def __init__(self, key: Ed25519PrivateKey | None, kid: str) -> None:
        self.key, self.kid = key, kid

    @classmethod
    def load(cls, run_dir: str | Path | None, kid: str, path: str | Path | None = None) -> "ControlSigner":
        """The signer ``kid`` with its key from ``path`` or ``RUN_DIR/keys`` (unsigned if there is none).

        :param run_dir: the run directory.
        :param kid: the key id (:data:`OPERATOR`, ``human:<id>``).
        :param path: an explicit private key file.
        :raises RoleKeyError: a key file that is not one.
        """
        return cls(load_private(run_dir, kid, path), kid)

    def payload(self, key_expr: str, command: str, sender: str, seq: int) -> bytes:
        """The encoded ``control`` message ``command`` for ``key_expr``, signed when there is a key.

        :param key_expr: the key it will be published on (signed: it cannot be re-published elsewhere).
        :param command: the command.
        :param sender: the envelope's sender.
        :param seq: the envelope's seq.
        """
        ts = time.time()
        if self.key is None:
            return control_payload(command, sender, seq, ts)
        sig = self.key.sign(signed_bytes(key_expr, command, sender, seq, ts, self.kid))
        return control_payload(command, sender, seq, ts, signer=self.kid, sig=sig)
