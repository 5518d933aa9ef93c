"""The KhGRL wire protocol (docs/protocol.md), defined once: key expressions and one class per message kind.

Senders build message instances and call :func:`encode`; receivers call :func:`decode` with the class they
expect and get an instance back, or a :class:`ProtocolError` that says why the payload was refused (schema
version, kind, size, types, dtypes, shapes, finiteness). Nothing outside this module touches msgpack (but
:mod:`khgrl.common.wire.control`, the numpy-free encoding of a ``control`` message).

Every payload is a msgpack map: the envelope ``v`` (schema version, the integer 1), ``kind``, ``sender``,
``seq``, ``ts``, then the fields of the kind. A decoded message carries its envelope in ``.envelope``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, fields
from typing import Any, Callable, TypeVar

import msgpack
import numpy as np
from khgrl.common.wire.checks import ProtocolError, RejectCounter, ident, pack_array, typ, unpack_array
from khgrl.common.wire.control import LAUNCHER
from khgrl.common.wire.frames import MAX_FRAME_BYTES
from khgrl.common.wire.keys import Keys
from khgrl.common.wire.messages import (
    ANY_DIMS,
    Ack,
    Control,
    Correction,
    Dims,
    EpisodeReport,
    Frame,
    Message,
    Scale,
    Status,
    TaskInfo,
    Transitions,
    Weights,
)

__all__ = ["SCHEMA_VERSION", "Keys", "Envelope", "encode", "decode", "decode_any", "KINDS", "ProtocolError",
           "RejectCounter", "pack_array", "unpack_array", "Message", "Transitions", "Ack", "Weights", "Correction",
           "Frame", "Scale", "EpisodeReport", "Status", "Control", "TaskInfo", "Dims", "ANY_DIMS", "with_base_seq",
           "LAUNCHER", "attribute_control"]

SCHEMA_VERSION = 1
M = TypeVar("M", bound=Message)

KINDS: dict[str, type[Message]] = {
    cls.KIND: cls
    for cls in (Transitions, Ack, Weights, Correction, Frame, Scale, EpisodeReport, Status, Control, TaskInfo)
}


@dataclass(frozen=True)
class Envelope:
    """What every message carries besides its fields."""

    kind: str
    sender: str
    seq: int
    ts: float


def _to_wire(value: Any, as_list: bool = False) -> Any:
    if as_list:  # a short vector: a list of floats on the wire
        return np.asarray(value, dtype=np.float64).reshape(-1).tolist()
    if isinstance(value, (str, bool, int, float)):  # most fields: nothing to convert
        return value
    if dataclasses.is_dataclass(value):  # (a field named in WIRE_OPTIONAL goes only when it holds something)
        d = dataclasses.asdict(value)
        for name in getattr(value, "WIRE_OPTIONAL", ()):
            if not d[name]:
                del d[name]
        return _to_wire(d)
    if isinstance(value, np.ndarray):
        return pack_array(value)
    if isinstance(value, dict):
        return {k: _to_wire(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_wire(v) for v in value]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return value


def encode(msg: Message, sender: str, seq: int, ts: float | None = None) -> bytes:
    """Pack one message (checked as a receiver would check it, so a sender cannot emit what peers refuse)."""
    if type(msg) not in KINDS.values():
        raise TypeError(f"not a protocol message: {type(msg).__name__}")
    ident("sender", sender)
    typ("seq", seq, int, low=0)
    body = {"v": SCHEMA_VERSION, "kind": msg.KIND, "sender": sender, "seq": int(seq),
            "ts": float(time.time() if ts is None else ts)}
    for f in fields(msg):
        if f.name == "envelope":
            continue
        value = getattr(msg, f.name)
        if value is not None:
            body[f.name] = _to_wire(value, f.name in msg.VECTORS)
    _validate(type(msg), body)  # the sender's own check, on the map itself: never publish what receivers reject
    payload = msgpack.packb(body, use_bin_type=True)
    if len(payload) > msg.max_bytes():
        raise ProtocolError(f"{len(payload)} bytes exceeds the {msg.KIND} limit of {msg.max_bytes()}")
    return payload


def _unpack(payload: Any, limit: int, kind: str) -> dict:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise ProtocolError("payload is not bytes")
    if len(payload) > limit:
        raise ProtocolError(f"{len(payload)} bytes exceeds the {kind} limit of {limit}")
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=limit, max_str_len=1 << 16,
                              max_array_len=1 << 16, max_map_len=1 << 12)
    except Exception as exc:  # noqa: BLE001 - msgpack raises several exception types for garbage
        raise ProtocolError(f"not msgpack: {type(exc).__name__}: {exc}") from None
    if not isinstance(msg, dict):
        raise ProtocolError("message is not a map")
    return msg


def _envelope(msg: dict, kind: str) -> Envelope:
    v = msg.get("v")
    if type(v) is not int or v != SCHEMA_VERSION:  # 1.0 and true are not the integer 1
        raise ProtocolError(f"schema version {v!r}, expected the integer {SCHEMA_VERSION}")
    if msg.get("kind") != kind:
        raise ProtocolError(f"kind {msg.get('kind')!r} on a {kind} topic")
    return Envelope(kind=kind, sender=ident("sender", msg.get("sender")), seq=typ("seq", msg.get("seq"), int, low=0),
                    ts=float(typ("ts", msg.get("ts"), (int, float))))


def decode(cls: type[M], payload: bytes, dims: Dims = ANY_DIMS) -> M:
    """Unpack and validate a message that must be of class ``cls``; raises :class:`ProtocolError` with the reason.

    :param dims: the observation and command sizes the receiver's task has (default: any, consistent).
    """
    return _validate(cls, _unpack(payload, cls.limit(dims), cls.KIND), dims)


def _validate(cls: type[M], msg: dict, dims: Dims = ANY_DIMS) -> M:
    """The checks of a received map (envelope, then the kind's fields): shared by :func:`decode` and the sender's
    own check in :func:`encode`."""
    env = _envelope(msg, cls.KIND)
    try:
        out = cls.from_wire(msg, dims)
    except ProtocolError:
        raise
    except Exception as exc:  # noqa: BLE001 - a malformed field that slipped past a type check
        raise ProtocolError(f"malformed {cls.KIND}: {type(exc).__name__}: {exc}") from None
    object.__setattr__(out, "envelope", env)
    return out


def decode_any(kind: str, payload: bytes) -> Message:
    """:func:`decode` by kind name (for tools that read several kinds)."""
    if kind not in KINDS:
        raise ProtocolError(f"unknown message kind {kind!r}")
    return decode(KINDS[kind], payload)


def with_base_seq(payload: bytes, base_seq: int, mac: Callable[[dict], bytes | dict] | None = None) -> bytes:
    """A stored ``transitions`` payload (one this process encoded, so its fields were checked then) re-stamped
    with the sender's current ``base_seq`` for a re-send: only the envelope and ``base_seq`` are looked at.

    :param payload: the encoded batch.
    :param base_seq: the oldest batch the sender holds now.
    :param mac: signs the re-stamped map: its ``mac`` (the run's key: ``run_key.wire_batch_mac``) or the fields to
        set (``data_keys.wire_sign``: ``mac``, ``signer``, ``sig``); None: no ``mac`` nor signature (those the payload
        had are dropped, as they no longer match).
    """
    msg = _unpack(payload, Transitions.MAX_BYTES + MAX_FRAME_BYTES, Transitions.KIND)  # (our own: any cameras)
    env = _envelope(msg, Transitions.KIND)
    base = typ("base_seq", base_seq, int, low=0)
    if base > env.seq:
        raise ProtocolError(f"base_seq {base} > seq {env.seq}")
    msg["base_seq"] = base
    for name in ("mac", "signer", "sig"):
        msg.pop(name, None)
    if mac is not None:
        signed = mac(msg)
        msg.update({"mac": signed} if isinstance(signed, bytes) else signed)
    return msgpack.packb(msg, use_bin_type=True)




def attribute_control(msg: Control, key: str, logger: logging.Logger) -> None:
    """Log a control command with who sent it: a warning for a ``stop`` or ``pause`` not from the launcher.

    :param msg: the decoded command.
    :param key: the key it came on.
    :param logger: the process's logger.
    """
    sender = msg.envelope.sender if msg.envelope is not None else "?"
    if msg.command in ("stop", "pause", "estop", "release") and sender != LAUNCHER:
        logger.warning("control %s from %r on %s: not from the launcher", msg.command, sender, key)
    else:
        logger.info("control: %s from %r on %s", msg.command, sender, key)
