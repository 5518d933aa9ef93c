"""The journal's record: one batch the learner stored, as :class:`~khgrl.learner.journal.Journal` writes it and
:mod:`khgrl.learner.journal_scan` reads it back.

A record is a 12-byte header -- ``b"KJ01"``, the body's length and its CRC-32 (little endian) -- and a body: a
4-byte length, a JSON map (``actor``, ``stream``, ``seq``, ``base``, ``first``, ``n``, ``obs``, ``out``,
``skipped``) and the arrays of the batch as raw little-endian bytes (``obs``, ``next_obs``, ``action``, ``reward``
float32; ``terminated``, ``truncated``, ``intervened``, ``clipped`` uint8); a camera batch's meta adds ``cams``
([name, H, W, C] each, in name order) and ``m`` (its frames), and its ``obs_frame``, ``next_frame`` (int32) and
frames (uint8, per camera) follow.
"""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
from khgrl.common.wire.frames import cameras_of
from khgrl.common.wire.protocol import Envelope, Transitions

__all__ = ["ARRAYS", "HEAD", "MAGIC", "MAX_BODY", "array_bytes", "encode_record", "decode_body"]

MAGIC = b"KJ01"
HEAD = struct.Struct("<4sII")  # magic, body length, crc32(body)
_META = struct.Struct("<I")
MAX_BODY = 64 * 2**20  # a length beyond this is a damaged header (a batch is at most 4 MiB on the wire)
# (field, dtype, columns: "obs" / "out" / None for a vector)
ARRAYS = (("obs", "<f4", "obs"), ("next_obs", "<f4", "obs"), ("action", "<f4", "out"), ("reward", "<f4", None),
          ("terminated", "|u1", None), ("truncated", "|u1", None), ("intervened", "|u1", None),
          ("clipped", "|u1", None))


def encode_record(msg: Transitions, seq: int, skipped: int = 0) -> bytes:
    """One journal record of a stored batch.

    :param msg: the batch
    :param seq: its seq in the actor's stream
    :param skipped: the batches its stream had skipped when it was stored (``ActorStream.skipped``: a replay tells
        the learner's own skips from batches the journal lost)
    """
    meta = {"actor": msg.actor, "stream": msg.stream or "", "seq": int(seq), "base": int(msg.base_seq or 0),
            "first": int(msg.first_step), "n": msg.n, "obs": int(msg.obs.shape[1]), "out": int(msg.action.shape[1]),
            "skipped": int(skipped)}
    if msg.frames is not None:  # a camera batch: its cameras and frame count (the arrays follow the others)
        meta.update(cams=[[k, *map(int, shape)] for k, shape in cameras_of(msg.frames)], m=_frame_count(msg))
    text = json.dumps(meta).encode()
    parts = [_META.pack(len(text)), text]
    parts += [np.ascontiguousarray(getattr(msg, name), dtype=dt).tobytes() for name, dt, _ in ARRAYS]
    parts += [np.ascontiguousarray(a).tobytes() for a in _frame_parts(msg)]
    body = b"".join(parts)
    return HEAD.pack(MAGIC, len(body), zlib.crc32(body)) + body


def array_bytes(msg: Transitions) -> int:
    """The bytes of a batch's arrays in its record (what a record waiting to be written holds in memory).

    :param msg: the batch
    """
    return sum(getattr(msg, name).nbytes for name, _, _ in ARRAYS) + sum(a.nbytes for a in _frame_parts(msg))


def _frame_count(msg: Transitions) -> int:
    return int(len(next(iter(msg.frames.values()))))


def _frame_parts(msg: Transitions) -> list[np.ndarray]:
    """A camera batch's arrays after :data:`ARRAYS` in a record: ``obs_frame``, ``next_frame`` (int32), then each
    camera's frames in name order (none: a vector batch)."""
    if msg.frames is None:
        return []
    return [np.asarray(msg.obs_frame, "<i4"), np.asarray(msg.next_frame, "<i4"),
            *(np.asarray(msg.frames[k], np.uint8) for k, _ in cameras_of(msg.frames))]


def decode_body(body: memoryview) -> tuple[Transitions, int | None]:
    """The batch of a record's body and the batches its stream had skipped then (None: a record of a learner
    before that was kept); ValueError, KeyError or TypeError if it does not decode.

    :param body: the record's body (after its header)
    """
    (mlen,) = _META.unpack_from(body, 0)
    meta = json.loads(bytes(body[_META.size:_META.size + mlen]))
    n, off = int(meta["n"]), _META.size + mlen
    arrays = {}
    for name, dt, cols in ARRAYS:
        shape = (n,) if cols is None else (n, int(meta[cols]))
        count = int(np.prod(shape))
        arr = np.frombuffer(body, dtype=dt, count=count, offset=off).reshape(shape)
        arrays[name] = arr
        off += arr.nbytes
    if "cams" in meta:  # a camera batch's frame indices and frames
        m = int(meta["m"])
        specs = [("obs_frame", "<i4", (n,)), ("next_frame", "<i4", (n,))]
        specs += [(f"cam:{c[0]}", "|u1", (m, *map(int, c[1:]))) for c in meta["cams"]]
        for name, dt, shape in specs:
            arr = np.frombuffer(body, dtype=dt, count=int(np.prod(shape)), offset=off).reshape(shape)
            arrays[name] = arr
            off += arr.nbytes
        arrays["frames"] = {k[4:]: arrays.pop(k) for k in list(arrays) if k.startswith("cam:")}
    if off != len(body):
        raise ValueError(f"{len(body) - off} bytes left over")
    msg = Transitions(actor=meta["actor"], first_step=int(meta["first"]), stream=meta["stream"] or None,
                      base_seq=int(meta["base"]), **arrays)
    object.__setattr__(msg, "envelope", Envelope(kind=Transitions.KIND, sender=meta["actor"], seq=int(meta["seq"]),
                                                 ts=0.0))
    return msg, (int(meta["skipped"]) if "skipped" in meta else None)
