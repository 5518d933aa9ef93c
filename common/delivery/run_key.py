"""The run's secret and the ``mac`` of acks and weights (docs/protocol.md, "Trust model": plain mode).

``khgrl up`` writes 32 random bytes to ``RUN_DIR/run.key`` (:data:`KEY_FILE`, mode 0600) before it starts any
process; a process started by hand reads the key from its ``--run-dir`` when the file is there (create one with
:func:`create` or ``head -c 32 /dev/urandom > RUN_DIR/run.key; chmod 600 RUN_DIR/run.key``). A learner with the
key puts a ``mac`` (keyed BLAKE2b, 32 bytes) over the canonical fields of every ack and weights message; an actor
with the key takes only acks and weights whose ``mac`` is right. A process on the router without the key --
another user of the machine reaching the loopback port, which cannot read a 0600 file -- can then no longer make
an actor drop its outbox (a forged ``durable``), stop it (a forged ``superseded``) or load other weights. Likewise
an actor with the key puts a ``mac`` on every ``transitions`` batch (:func:`batch_mac`, :func:`wire_batch_mac` for a
re-stamped payload) and a learner with the key refuses a batch without a right one before it is stored or its
actor id admitted: fake actor ids cost only their decoding. A process without the key behaves as before (no
``mac`` sent, none checked).

A ``mac`` binds the message's fields, not its time: a genuine earlier ack replayed says nothing new (``durable``
never moves back, and an ack of a stale epoch is refused by the actor's checks).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import secrets
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["KEY_FILE", "KEY_BYTES", "MAC_BYTES", "RunKeyError", "create", "load", "mac_of", "sign", "check",
           "batch_mac", "wire_batch_mac", "sign_batch"]

log = logging.getLogger("khgrl.trust")

KEY_FILE = "run.key"
KEY_BYTES = 32
MAC_BYTES = 32


class RunKeyError(ValueError):
    """``RUN_DIR/run.key`` exists but is not a key (not 32 bytes, or unreadable)."""


def create(run_dir: str | Path, *, fresh: bool = False) -> bytes:
    """Write a new key to ``RUN_DIR/run.key`` (mode 0600, atomically) unless one is there and ``fresh`` is false;
    returns the key now in the file.

    :param run_dir: the run directory (made if missing).
    :param fresh: replace an existing key (a new run in the directory).
    """
    path = Path(run_dir) / KEY_FILE
    if path.is_file() and not fresh:
        key = load(run_dir)
        if key is not None:
            return key
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{KEY_FILE}.{os.getpid()}.tmp")
    key = secrets.token_bytes(KEY_BYTES)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, key)
    finally:
        os.close(fd)
    os.chmod(tmp, 0o600)
    os.replace(tmp, path)
    return key


def load(run_dir: str | Path | None) -> bytes | None:
    """The key in ``RUN_DIR/run.key`` (None: no such file). A file readable by other users is used, with a warning.

    :param run_dir: the run directory (None: no key).
    :raises RunKeyError: the file is there but is not a key.
    """
    if not run_dir:
        return None
    path = Path(run_dir) / KEY_FILE
    if not path.is_file():
        return None
    try:
        key = path.read_bytes()
        mode = path.stat().st_mode & 0o077
    except OSError as exc:
        raise RunKeyError(f"{path}: {exc}") from None
    if len(key) != KEY_BYTES:
        raise RunKeyError(f"{path}: {len(key)} bytes, expected a key of {KEY_BYTES}")
    if mode:
        log.warning("%s is readable by other users (mode %o): anyone who reads it can forge acks and weights", path,
                    path.stat().st_mode & 0o777)
    return key


def _canonical(fields: list) -> bytes:
    """The fields as bytes that only these values give (JSON: ids are strings without quotes or escapes)."""
    return json.dumps(fields, separators=(",", ":"), ensure_ascii=True).encode()


def _ack_fields(msg: Any) -> list:
    return ["ack", msg.actor, msg.received, msg.durable, msg.trained, msg.version, msg.epoch, msg.stream, msg.task,
            msg.superseded]


# the arrays of a ``transitions`` batch, in the order the mac takes them
BATCH_ARRAYS = ("obs", "next_obs", "action", "reward", "terminated", "truncated", "intervened", "clipped")


def _batch_digest(key: bytes, head: list, arrays: list[tuple[str, list, Any]]) -> bytes:
    """The ``mac`` of a batch: its scalar fields and each array's dtype and shape as canonical JSON, then the
    arrays' bytes in :data:`BATCH_ARRAYS` order."""
    h = hashlib.blake2b(key=key, digest_size=MAC_BYTES, person=b"khgrl-batch")
    h.update(_canonical(["transitions", *head, [[dt, shape] for dt, shape, _ in arrays]]))
    for _, _, data in arrays:
        h.update(data)
    return h.digest()


def _array_part(arr: np.ndarray) -> tuple[str, list, Any]:
    """An array as the wire carries it (``pack_array``): dtype string, shape, C-order bytes (no copy if it can)."""
    arr = np.ascontiguousarray(arr)
    return arr.dtype.str, list(arr.shape), arr.data.cast("B") if arr.size else b""


def _frame_head(names: Any) -> list:
    """A camera batch's cameras as one more head field (nothing without frames: a vector batch's mac is as it was)."""
    return [] if names is None else [["frames", sorted(names)]]


def _frame_arrays(msg: Any) -> list[tuple[str, list, Any]]:
    """A camera batch's ``obs_frame``, ``next_frame`` and frames (cameras in name order) as :func:`_array_part`."""
    if msg.frames is None:
        return []
    return [_array_part(msg.obs_frame), _array_part(msg.next_frame), *(_array_part(msg.frames[k])
                                                                        for k in sorted(msg.frames))]


def _wire_frame_arrays(m: dict) -> list[tuple[str, list, Any]]:
    """:func:`_frame_arrays` of a batch's msgpack map."""
    frames = m.get("frames")
    if frames is None:
        return []
    parts = [m["obs_frame"], m["next_frame"], *(frames[k] for k in sorted(frames))]
    return [(a["dtype"], list(a["shape"]), a["data"]) for a in parts]


def _vouch_part(vouch: Any) -> list:
    """A batch's ``vouch`` evidence (khgrl.common.wire.batch) as one more head field: the hex BLAKE2b of its entries
    as canonical JSON (signatures as hex); nothing without evidence (so a batch without it has the mac it had)."""
    if vouch is None:
        return []
    entries = [[v.hex() if isinstance(v, bytes) else list(v) if isinstance(v, tuple) else v for v in e] for e in vouch]
    return [hashlib.blake2b(_canonical(["vouch", entries]), digest_size=16).hexdigest()]


def batch_mac(msg: Any, key: bytes, seq: int) -> bytes:
    """The ``mac`` of a ``transitions`` batch sent with envelope ``seq``: over actor, stream, seq, first_step,
    base_seq, task digest and the arrays (dtype, shape, bytes; a camera batch's frame indices and frames too), its own
    ``mac`` left out.

    :param msg: a :class:`~khgrl.common.wire.messages.Transitions`.
    :param key: the run's key.
    :param seq: the envelope's seq (the batch's number in its stream).
    """
    head = [msg.actor, msg.stream, int(seq), msg.first_step, msg.base_seq, msg.task, *_vouch_part(msg.vouch),
            *_frame_head(msg.frames)]
    return _batch_digest(key, head, [_array_part(getattr(msg, n)) for n in BATCH_ARRAYS] + _frame_arrays(msg))


def wire_batch_mac(m: dict, key: bytes) -> bytes:
    """:func:`batch_mac` of a batch as its msgpack map (one this process encoded: a re-stamped ``base_seq``).

    :param m: the map (envelope and fields; arrays as ``{dtype, shape, data}``).
    :param key: the run's key.
    """
    head = [m.get(f) for f in ("actor", "stream", "seq", "first_step", "base_seq", "task")]
    head += _vouch_part(m.get("vouch")) + _frame_head(m.get("frames"))
    arrays = [(m[n]["dtype"], list(m[n]["shape"]), m[n]["data"]) for n in BATCH_ARRAYS]
    return _batch_digest(key, head, arrays + _wire_frame_arrays(m))


def sign_batch(msg: Any, key: bytes | None, seq: int) -> Any:
    """``msg`` (a ``transitions`` batch to be sent with envelope ``seq``) with its ``mac`` set (unchanged without a
    key).

    :param msg: the batch.
    :param key: the run's key (None: no mac).
    :param seq: the envelope's seq.
    """
    return msg if key is None else msg.replace(mac=batch_mac(msg, key, seq))


def mac_of(msg: Any, key: bytes) -> bytes:
    """The ``mac`` of an ack, weights or (received: its envelope's seq) transitions message under ``key`` (its own
    ``mac`` field left out).

    :param msg: an :class:`~khgrl.common.wire.messages.Ack`, :class:`~khgrl.common.wire.messages.Weights` or
        decoded :class:`~khgrl.common.wire.messages.Transitions`.
    :param key: the run's key.
    """
    if msg.KIND == "transitions":
        return batch_mac(msg, key, msg.envelope.seq)
    h = hashlib.blake2b(key=key, digest_size=MAC_BYTES, person=f"khgrl-{msg.KIND}".encode()[:16])
    if msg.KIND == "ack":
        h.update(_canonical(_ack_fields(msg)))
        return h.digest()
    names = sorted(msg.tensors)
    arrays = [np.ascontiguousarray(msg.tensors[n], dtype="<f4") for n in names]
    head = [msg.KIND, msg.version, msg.epoch, sorted(msg.trained.items()),
            [[n, list(a.shape)] for n, a in zip(names, arrays)]]
    h.update(_canonical(head))
    for a in arrays:
        h.update(a.data if a.size else b"")
    return h.digest()


def sign(msg: Any, key: bytes | None) -> Any:
    """``msg`` with its ``mac`` set (unchanged without a key).

    :param msg: an ack or weights message.
    :param key: the run's key (None: no mac).
    """
    return msg if key is None else msg.replace(mac=mac_of(msg, key))


def check(msg: Any, key: bytes | None) -> str | None:
    """Why ``msg`` is not authentic under ``key`` (None: it is, or there is no key to check with).

    :param msg: a received ack, weights or transitions message.
    :param key: the run's key (None: nothing is checked).
    """
    if key is None:
        return None
    signer = "an actor" if msg.KIND == "transitions" else "the learner"
    if msg.mac is None:
        return f"{msg.KIND} without a mac (this process has the run's key: {signer} would sign it)"
    if not secrets.compare_digest(msg.mac, mac_of(msg, key)):
        return f"{msg.KIND} with a wrong mac (not from {signer} with the run's key)"
    return None
