"""The payload of a ``control`` message, built without numpy (docs/protocol.md, "control"): the one place the
launcher, ``khgrl stop``, ``khgrl supervise`` and the benchmarks encode their commands, so ``khgrl stop --now``
starts fast (README, "On a real robot"). The bytes are exactly :func:`khgrl.common.wire.protocol.encode`'s for a
:class:`~khgrl.common.wire.messages.Control` (tests/unit/test_supervision_parts.py checks it).

Besides the commands of :data:`~khgrl.common.wire.messages.COMMANDS` that a person gives, the supervisor's heartbeat
(:mod:`khgrl.deploy.run.supervise`) is a control message on ``control/actor``: ``heartbeat`` while the run's e-stop is
released, ``heartbeat-estop`` while it is pressed.
"""

from __future__ import annotations

import time

import msgpack

__all__ = ["control_payload", "HEARTBEATS", "HEARTBEAT", "HEARTBEAT_ESTOP", "LAUNCHER"]

SCHEMA_VERSION = 1  # (khgrl.common.wire.protocol.SCHEMA_VERSION)
LAUNCHER = "launcher"  # the sender id of the launcher's (the operator's side's) control messages
HEARTBEAT, HEARTBEAT_ESTOP = "heartbeat", "heartbeat-estop"
HEARTBEATS = (HEARTBEAT, HEARTBEAT_ESTOP)


def control_payload(command: str, sender: str, seq: int, ts: float | None = None, signer: str | None = None,
                    sig: bytes | None = None) -> bytes:
    """The encoded ``control`` message ``command`` from ``sender``, number ``seq`` (signed: with ``signer`` and
    ``sig``, :mod:`khgrl.common.delivery.control_sign`).

    :param command: one of :data:`~khgrl.common.wire.messages.COMMANDS` (not checked here: the receivers check).
    :param sender: the sender's id (``launcher`` for the operator's side).
    :param seq: the sender's sequence number.
    :param ts: the timestamp (default: now).
    :param signer: the signer's key id (None: unsigned).
    :param sig: its signature (with ``signer``).
    """
    body = {"v": SCHEMA_VERSION, "kind": "control", "sender": sender, "seq": int(seq),
            "ts": float(time.time() if ts is None else ts), "command": command}
    if signer is not None:
        body["signer"], body["sig"] = signer, bytes(sig)
    return msgpack.packb(body, use_bin_type=True)
