"""Field-level wire checks shared by the message classes of :mod:`khgrl.common.wire.protocol`: typed scalars, ids,
vectors, arrays (``{"dtype", "shape", "data"}`` maps), and the counted, rate-limited log of rejected messages.

Nothing here unpickles anything: arrays are raw little-endian bytes with an allowed dtype and a checked shape.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from typing import Any

import numpy as np
from khgrl.common.wire.keys import MAX_ID_LEN

__all__ = ["ProtocolError", "RejectCounter", "pack_array", "unpack_array", "typ", "ident", "vec", "opt", "exact_bytes",
           "MAX_ID_LEN"]

log = logging.getLogger("khgrl.protocol")

_DTYPES = {"<f4": np.float32, "<f8": np.float64, "|u1": np.uint8, "<i4": np.int32, "<i8": np.int64}


class ProtocolError(ValueError):
    """A message that does not follow the protocol; the text says why."""


def pack_array(arr: np.ndarray) -> dict:
    """An array as a wire map: little-endian, C order, one of the allowed dtypes (bool goes as ``|u1``)."""
    arr = np.ascontiguousarray(arr)
    dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    key = dt.str
    if key not in _DTYPES:
        if arr.dtype == np.bool_:
            arr, key = arr.astype(np.uint8), "|u1"
            dt = arr.dtype
        else:
            raise ProtocolError(f"dtype {arr.dtype} is not allowed on the wire")
    return {"dtype": key, "shape": list(arr.shape), "data": arr.astype(dt, copy=False).tobytes()}


def unpack_array(obj: Any, name: str, *, dtype: str | tuple[str, ...], shape: tuple, finite: bool = True) -> np.ndarray:
    """Decode and check an array field. ``shape`` entries: an int (exact) or None (any size)."""
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise ProtocolError(f"{name}: not an array map with dtype, shape, data")
    dt, shp, data = obj["dtype"], obj["shape"], obj["data"]
    allowed = (dtype,) if isinstance(dtype, str) else dtype
    if dt not in allowed:
        raise ProtocolError(f"{name}: dtype {dt!r} not in {allowed}")
    if not isinstance(shp, list) or not all(type(d) is int and 0 <= d <= 1 << 26 for d in shp):
        raise ProtocolError(f"{name}: bad shape {shp!r}")
    if len(shp) != len(shape):
        raise ProtocolError(f"{name}: expected {len(shape)} dimensions, got shape {shp}")
    for want, got in zip(shape, shp):
        if want is not None and want != got:
            raise ProtocolError(f"{name}: expected shape {shape}, got {shp}")
    if not isinstance(data, bytes):
        raise ProtocolError(f"{name}: data must be bytes")
    np_dt = np.dtype(_DTYPES[dt]).newbyteorder("<")
    if len(data) != int(np.prod(shp, dtype=np.int64)) * np_dt.itemsize:
        raise ProtocolError(f"{name}: {len(data)} bytes do not match shape {shp} of {dt}")
    arr = np.frombuffer(data, dtype=np_dt).reshape(shp)
    if finite and arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise ProtocolError(f"{name}: contains NaN or inf")
    return arr


def typ(name: str, value: Any, types, *, low=None, high=None):
    """``value`` if it has one of ``types`` (bool is never an int or float here) and lies in [low, high]."""
    allowed = types if isinstance(types, tuple) else (types,)
    if isinstance(value, bool) and bool not in allowed:
        raise ProtocolError(f"{name}: expected {_names(allowed)}, got bool")
    if not isinstance(value, allowed):
        raise ProtocolError(f"{name}: expected {_names(allowed)}, got {type(value).__name__}")
    if isinstance(value, float) and not np.isfinite(value):
        raise ProtocolError(f"{name}: not finite")
    if low is not None and value < low:
        raise ProtocolError(f"{name}: {value} < {low}")
    if high is not None and value > high:
        raise ProtocolError(f"{name}: {value} > {high}")
    return value


def _names(types: tuple) -> str:
    return "/".join(t.__name__ for t in types)


def ident(name: str, value: Any) -> str:
    """An id usable as one key chunk: 1-64 characters, no ``/ * $ ? #`` or space."""
    typ(name, value, str)
    if not value or len(value) > MAX_ID_LEN or any(c in value for c in "/*$?# "):
        raise ProtocolError(f"{name}: bad identifier {value!r}")
    return value


def vec(name: str, value: Any, n: int) -> np.ndarray:
    """A list of ``n`` finite numbers as float64."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ProtocolError(f"{name}: expected a list of {n} numbers")
    return np.array([typ(f"{name}[{i}]", v, (int, float)) for i, v in enumerate(value)], dtype=np.float64)


def exact_bytes(size: int):
    """A check of a bytes field of exactly ``size`` bytes (a ``mac``, a ``sig``)."""
    def check(name: str, value: Any) -> bytes:
        if len(typ(name, value, bytes)) != size:
            raise ProtocolError(f"{name}: {len(value)} bytes, expected {size}")
        return value
    return check


def opt(m: dict, name: str, check, *args, **kwargs):
    """``check(name, m[name], ...)`` if the optional field is present (and not nil), else None."""
    if m.get(name) is None:
        return None
    return check(name, m[name], *args, **kwargs)


class RejectCounter:
    """Counts rejected messages by kind and reason, and logs them rate-limited: the first ``first`` distinct reasons
    of a kind each get a line; after that at most one line per kind every ``every`` seconds, saying how many were
    rejected since the last line and the latest reason. A flood of garbage (random bytes give a new reason each
    time) costs a few lines a minute and a bounded amount of memory (at most ``max_reasons`` reasons are told apart
    per kind; the rest count as "other").

    :param role: who rejects (in the log lines)
    :param first: distinct reasons per kind logged at once
    :param every: seconds between the later lines of a kind
    :param max_reasons: reasons told apart per kind
    :param clock: monotonic seconds
    """

    def __init__(self, role: str, *, first: int = 32, every: float = 10.0, max_reasons: int = 32,
                 clock=time.monotonic) -> None:
        self.role = role
        self.first, self.every, self.max_reasons, self.clock = first, every, max_reasons, clock
        self.counts: Counter = Counter()
        self.logged = 0  # lines written
        self._reasons: dict[str, set[str]] = {}
        self._last: dict[str, tuple[float, int]] = {}  # kind -> (time of its last line, its count then)
        self._lock = threading.Lock()

    def reject(self, kind: str, key: str, err: Exception) -> None:
        reason = str(err)[:160]
        with self._lock:
            self.counts[kind] += 1
            n_kind = self.counts[kind]
            seen = self._reasons.setdefault(kind, set())
            new = reason not in seen and len(seen) < self.max_reasons
            if new:
                seen.add(reason)
            self.counts[(kind, reason if reason in seen else "other")] += 1
            now = self.clock()
            last_t, last_n = self._last.get(kind, (-float("inf"), 0))
            if new and len(seen) <= self.first:
                line = f"(#{n_kind} of this kind): {err}"
            elif now - last_t >= self.every:
                line = f"(#{n_kind} of this kind, {n_kind - last_n} since the last line): {err}"
            else:
                return
            self._last[kind] = (now, n_kind)
            self.logged += 1
        log.warning("%s rejected %s message on %s %s", self.role, kind, key, line)

    @property
    def total(self) -> int:
        return sum(v for k, v in self.counts.items() if isinstance(k, str))

    def by_kind(self) -> dict[str, int]:
        return {k: v for k, v in self.counts.items() if isinstance(k, str)}
