"""What every message kind of the wire protocol shares (:mod:`khgrl.common.wire.messages`): the sizes a receiver
expects, the base class, and the checks of vectors and of ``mac`` / ``sig`` bytes."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from khgrl.common.wire.checks import exact_bytes, vec
from khgrl.common.wire.descriptor import MAX_DIM

__all__ = ["Dims", "ANY_DIMS", "Message", "MAC_BYTES", "SIG_BYTES"]


@dataclass(frozen=True)
class Dims:
    """The sizes a receiver expects (from the run's task descriptor): the policy's observation (a camera task's:
    its state vector), the command O (= the policy's action), the KMP grid's N and the cameras. None: any size up to
    the protocol's bound, consistent within the message."""

    obs: int | None = None
    out: int | None = None
    horizon: int | None = None  # N, the KMP grid's points (a frame's scene arrays have N rows)
    cameras: tuple[tuple[str, tuple[int, int, int]], ...] | None = None  # (name, (H, W, C)) in name order; (): none

    @classmethod
    def of_task(cls, task) -> "Dims":
        """The sizes of a task descriptor's batches (observation, command, cameras).

        :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor`
        """
        cams = getattr(task, "cameras", None) or {}
        return cls(obs=task.obs_dim, out=task.out_dim, cameras=tuple((k, tuple(cams[k])) for k in sorted(cams)))


ANY_DIMS = Dims()


def _vec(name: str, value: Any, n: int | None) -> np.ndarray:
    """A vector of ``n`` numbers, or (n None) of 1..MAX_DIM numbers."""
    if n is None:
        n = len(value) if isinstance(value, (list, tuple)) and 1 <= len(value) <= MAX_DIM else -1
    return vec(name, value, n)


def _any_vec(name: str, value: Any, most: int) -> np.ndarray:
    """A vector of 1..``most`` finite numbers."""
    n = len(value) if isinstance(value, (list, tuple)) and 1 <= len(value) <= most else -1
    return vec(name, value, n)


MAC_BYTES = 32  # the ``mac`` of acks, weights and transitions
SIG_BYTES = 64  # the ``sig`` of control, acks, weights and transitions (Ed25519)


_mac, _sig = exact_bytes(MAC_BYTES), exact_bytes(SIG_BYTES)


@dataclass(frozen=True)
class Message:
    KIND: ClassVar[str] = ""
    MAX_BYTES: ClassVar[int] = 4096
    VECTORS: ClassVar[tuple[str, ...]] = ()  # fields sent as lists of numbers (the others' arrays as array maps)
    envelope: Any = field(default=None, kw_only=True, compare=False, repr=False)

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)

    @classmethod
    def limit(cls, dims: Dims = ANY_DIMS) -> int:
        """Bytes a message of this kind may take for a receiver of ``dims`` (default: :attr:`MAX_BYTES`).

        :param dims: the receiver's sizes
        """
        return cls.MAX_BYTES

    def max_bytes(self) -> int:
        """Bytes this message may take encoded (its sender's check; default: :attr:`MAX_BYTES`)."""
        return self.MAX_BYTES

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS):
        raise NotImplementedError
