"""The ``transitions`` message: a batch of one actor's transitions, and the evidence that a human vouched for its
intervened rows (``vouch``: :mod:`khgrl.common.delivery.vouching` makes and checks it). A camera task's batch
carries its images as frames, each once (:mod:`khgrl.common.wire.frames`); its size limit grows with the cameras
(:meth:`Transitions.limit`), a vector task's is :attr:`Transitions.MAX_BYTES`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from khgrl.common.wire.base import ANY_DIMS, Dims, Message, _mac, _sig
from khgrl.common.wire.checks import ProtocolError, ident, opt, typ, unpack_array, vec
from khgrl.common.wire.descriptor import MAX_DIM
from khgrl.common.wire.frames import cameras_of, check_frames, frame_bytes, max_frames

__all__ = ["Transitions", "MAX_BATCH", "Evidence", "DEMO_ENTRY", "HUMAN_ENTRY"]

MAX_BATCH = 4096  # transitions per batch message
# a ``vouch`` entry: (row,) for a row of the run's own demonstrations (a0's), or the signed correction that drove
# the row: (row, client, seq, episode, t, step, p_h, sig) -- the correction's fields and envelope seq, and the
# client's Ed25519 signature of them (khgrl.common.delivery.vouching.correction_bytes)
DEMO_ENTRY, HUMAN_ENTRY = 1, 8
Evidence = tuple  # one entry, as above


def _int_or_none(name: str, value: Any) -> int | None:
    return None if value is None else typ(name, value, int, low=0)


def _vouch(name: str, value: Any, n: int) -> tuple[Evidence, ...]:
    """The ``vouch`` evidence of a batch of ``n`` rows, checked: at most one entry per row, rows ascending."""
    if not isinstance(value, (list, tuple)) or len(value) > n:
        raise ProtocolError(f"{name}: expected a list of at most {n} entries")
    out, last = [], -1
    for i, e in enumerate(value):
        if not isinstance(e, (list, tuple)) or len(e) not in (DEMO_ENTRY, HUMAN_ENTRY):
            raise ProtocolError(f"{name}[{i}]: expected [row] or [row, client, seq, episode, t, step, p_h, sig]")
        row = typ(f"{name}[{i}].row", e[0], int, low=last + 1, high=n - 1)
        last = row
        if len(e) == DEMO_ENTRY:
            out.append((row,))
            continue
        p_h = e[6]
        if not isinstance(p_h, (list, tuple)) or not 1 <= len(p_h) <= MAX_DIM:
            raise ProtocolError(f"{name}[{i}].p_h: expected 1..{MAX_DIM} numbers")
        p_h = tuple(float(v) for v in vec(f"{name}[{i}].p_h", list(p_h), len(p_h)))
        out.append((row, ident(f"{name}[{i}].client", e[1]), typ(f"{name}[{i}].seq", e[2], int, low=0),
                    _int_or_none(f"{name}[{i}].episode", e[3]), _int_or_none(f"{name}[{i}].t", e[4]),
                    _int_or_none(f"{name}[{i}].step", e[5]), p_h, _sig(f"{name}[{i}].sig", e[7])))
    return tuple(out)


_FLAG_FIELDS = ("terminated", "truncated", "intervened", "clipped")


@dataclass(frozen=True, eq=False)
class Transitions(Message):
    """A batch of one actor's transitions, in order; ``seq`` (envelope) numbers the actor's batches."""

    KIND: ClassVar[str] = "transitions"
    MAX_BYTES: ClassVar[int] = 4 * 1024 * 1024
    actor: str
    first_step: int  # the actor's running index of the first transition
    obs: np.ndarray  # (n, obs size) float32
    next_obs: np.ndarray
    action: np.ndarray  # (n, O) float32 in [-1, 1] (the human's a_h on intervened steps)
    reward: np.ndarray  # (n,) float32
    terminated: np.ndarray  # (n,) uint8 0/1
    truncated: np.ndarray
    intervened: np.ndarray
    clipped: np.ndarray
    base_seq: int | None = None  # the oldest batch the actor still holds
    stream: str | None = None  # random id of the actor incarnation
    task: str | None = None  # the digest of the actor's task descriptor: required on the wire
    mac: bytes | None = None  # keyed BLAKE2b of the other fields and the envelope's seq under the run's key
    signer: str | None = None  # the key id that signed it (``actor:<actor>``; khgrl.common.delivery.data_keys)
    sig: bytes | None = None  # its Ed25519 signature
    vouch: tuple[Evidence, ...] | None = None  # per intervened row, the evidence a human drove it (see above)
    frames: dict[str, np.ndarray] | None = None  # a camera task's: camera -> uint8 (m, H, W, C), each frame once
    obs_frame: np.ndarray | None = None  # (n,) int32: the frame each row observed (khgrl.common.wire.frames)
    next_frame: np.ndarray | None = None  # (n,) int32: the frame each row observed next

    @property
    def n(self) -> int:
        return int(self.reward.shape[0])

    @classmethod
    def limit(cls, dims: Dims = ANY_DIMS) -> int:
        """Bytes a batch may take for a receiver of ``dims``: :attr:`MAX_BYTES`, plus a camera task's frames (as
        many as :func:`~khgrl.common.wire.frames.max_frames` allows). A receiver that knows no cameras (``dims``
        None: any) takes a vector batch's size: one that decodes camera batches knows its task's cameras.

        :param dims: the receiver's sizes
        """
        if not dims.cameras:
            return cls.MAX_BYTES
        return cls.MAX_BYTES + frame_bytes(dims.cameras) * max_frames(dims.cameras, MAX_BATCH)

    def max_bytes(self) -> int:
        """Bytes this batch may take encoded: :meth:`limit` of its own cameras."""
        return self.limit(Dims(cameras=cameras_of(self.frames) if self.frames else ()))

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Transitions":
        spec = {"obs": ("<f4", (None, dims.obs)), "next_obs": ("<f4", (None, dims.obs)),
                "action": ("<f4", (None, dims.out)), "reward": ("<f4", (None,))}
        spec.update({f: ("|u1", (None,)) for f in _FLAG_FIELDS})
        arrays = {name: unpack_array(m.get(name), name, dtype=dt, shape=shape) for name, (dt, shape) in spec.items()}
        n = arrays["reward"].shape[0]
        for name, arr in arrays.items():
            if arr.shape[0] != n:
                raise ProtocolError(f"{name}: {arr.shape[0]} rows, expected {n}")
        if arrays["obs"].shape[1] != arrays["next_obs"].shape[1] or not 1 <= arrays["obs"].shape[1] <= 4 * MAX_DIM:
            raise ProtocolError(f"obs/next_obs widths {arrays['obs'].shape[1]}/{arrays['next_obs'].shape[1]}")
        if not 1 <= arrays["action"].shape[1] <= MAX_DIM:
            raise ProtocolError(f"action width {arrays['action'].shape[1]} outside [1, {MAX_DIM}]")
        if not 1 <= n <= MAX_BATCH:
            raise ProtocolError(f"batch of {n} transitions outside [1, {MAX_BATCH}]")
        if np.any(np.abs(arrays["action"]) > 1.0 + 1e-6):
            raise ProtocolError("actions outside [-1, 1]")
        for flag in _FLAG_FIELDS:
            if np.any(arrays[flag] > 1):
                raise ProtocolError(f"{flag}: flags must be 0/1")
        base = opt(m, "base_seq", typ, int, low=0)
        if base is not None and base > m.get("seq", 0):
            raise ProtocolError(f"base_seq {base} > seq {m.get('seq')}")
        actor, first = ident("actor", m.get("actor")), typ("first_step", m.get("first_step"), int, low=0)
        if m.get("task") is None:
            raise ProtocolError("task: missing (the digest of the actor's task descriptor is required)")
        frames, obs_frame, next_frame = check_frames(m, dims.cameras, n, arrays["terminated"] | arrays["truncated"],
                                                     MAX_BATCH)
        return cls(actor=actor, first_step=first, base_seq=base, stream=opt(m, "stream", ident),
                   task=ident("task", m.get("task")), mac=opt(m, "mac", _mac), signer=opt(m, "signer", ident),
                   sig=opt(m, "sig", _sig), vouch=opt(m, "vouch", _vouch, n), frames=frames, obs_frame=obs_frame,
                   next_frame=next_frame, **arrays)
