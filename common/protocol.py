"""The KhGRL wire protocol: key expressions, msgpack message schemas and the validator every receiver uses.

Written up for client authors in ``docs/protocol.md``. Rules:

* every message is a msgpack map with ``v`` (schema version), ``kind``, ``sender``, ``seq`` (per sender and
  kind, starting at 0) and ``ts`` (sender's wall clock, seconds since the epoch), plus the kind's fields;
* arrays travel as maps ``{"dtype": "<f4" | "<f8" | "|u1" | "<i8", "shape": [...], "data": bytes}``
  (little-endian, C order);
* nothing is ever unpickled; :func:`decode` checks schema version, kind, field types, array dtype and
  shape, finiteness and size, and raises :class:`ProtocolError` with the reason. Receivers count and log
  rejected messages and carry on (:class:`RejectCounter`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable

import msgpack
import numpy as np

__all__ = [
    "SCHEMA_VERSION",
    "ProtocolError",
    "Keys",
    "encode",
    "decode",
    "pack_array",
    "unpack_array",
    "RejectCounter",
    "MAX_BYTES",
    "OBS_DIM",
    "ACT_DIM",
]

log = logging.getLogger("khgrl.protocol")

SCHEMA_VERSION = 1
OBS_DIM = 5  # passage world observation (see common.env)
ACT_DIM = 2
MAX_BATCH = 4096  # transitions per batch message
MAX_ID_LEN = 64

# Largest accepted payload per kind (bytes); anything larger is rejected before unpacking.
MAX_BYTES = {
    "transitions": 4 * 1024 * 1024,
    "ack": 4096,
    "weights": 64 * 1024 * 1024,
    "correction": 4096,
    "frame": 64 * 1024,
    "scale": 1024 * 1024,
    "episode": 16 * 1024,
    "status": 16 * 1024,
    "control": 4096,
}

_DTYPES = {"<f4": np.float32, "<f8": np.float64, "|u1": np.uint8, "<i8": np.int64}


class ProtocolError(ValueError):
    """A message that does not follow the protocol; the text says why."""


class Keys:
    """Key expressions of one run: everything lives under ``khgrl/<run>/``."""

    def __init__(self, run: str) -> None:
        if not run or any(c in run for c in "/*$?#") or len(run) > MAX_ID_LEN:
            raise ValueError(f"run id must be a non-empty key chunk without / * $ ? #, got {run!r}")
        self.run = run
        self.root = f"khgrl/{run}"

    def transitions(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/transitions"

    def frame(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/frame"

    def scale(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/scale"

    def episode(self, actor: str = "*") -> str:
        return f"{self.root}/actor/{actor}/episode"

    def ack(self, actor: str = "*") -> str:
        return f"{self.root}/learner/ack/{actor}"

    @property
    def weights(self) -> str:
        return f"{self.root}/learner/weights"

    def correction(self, client: str = "*") -> str:
        return f"{self.root}/human/{client}/correction"

    def status(self, role: str = "*", ident: str = "*") -> str:
        return f"{self.root}/status/{role}/{ident}"

    def control(self, target: str = "*") -> str:
        return f"{self.root}/control/{target}"

    def alive(self, role: str = "*", ident: str = "*") -> str:
        return f"{self.root}/alive/{role}/{ident}"

    @staticmethod
    def last_chunk(key: str, index: int) -> str:
        return str(key).split("/")[index]


# --------------------------------------------------------------------------------------- arrays
def pack_array(arr: np.ndarray) -> dict:
    arr = np.ascontiguousarray(arr)
    dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    key = dt.str
    if key not in _DTYPES:
        if arr.dtype == np.bool_:
            arr, key = arr.astype(np.uint8), "|u1"
        else:
            raise ProtocolError(f"dtype {arr.dtype} is not allowed on the wire")
    return {"dtype": key, "shape": list(arr.shape), "data": arr.astype(dt, copy=False).tobytes()}


def unpack_array(obj: Any, name: str, *, dtype: str | tuple[str, ...], shape: tuple, finite: bool = True) -> np.ndarray:
    """Decode and check an array field. ``shape`` entries: an int (exact), None (any size), or a str
    (a named dimension that must match across fields -- checked by the caller)."""
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise ProtocolError(f"{name}: not an array map with dtype, shape, data")
    dt, shp, data = obj["dtype"], obj["shape"], obj["data"]
    allowed = (dtype,) if isinstance(dtype, str) else dtype
    if dt not in allowed:
        raise ProtocolError(f"{name}: dtype {dt!r} not in {allowed}")
    if not isinstance(shp, list) or not all(isinstance(d, int) and 0 <= d <= 1 << 26 for d in shp):
        raise ProtocolError(f"{name}: bad shape {shp!r}")
    if len(shp) != len(shape):
        raise ProtocolError(f"{name}: expected {len(shape)} dimensions, got shape {shp}")
    for want, got in zip(shape, shp):
        if isinstance(want, int) and want != got:
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


# -------------------------------------------------------------------------------------- schemas
def _typ(name: str, value: Any, types, *, low=None, high=None):
    if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        raise ProtocolError(f"{name}: expected {types}, got bool")
    if not isinstance(value, types):
        raise ProtocolError(f"{name}: expected {types}, got {type(value).__name__}")
    if isinstance(value, float) and not np.isfinite(value):
        raise ProtocolError(f"{name}: not finite")
    if low is not None and value < low:
        raise ProtocolError(f"{name}: {value} < {low}")
    if high is not None and value > high:
        raise ProtocolError(f"{name}: {value} > {high}")
    return value


def _ident(name: str, value: Any) -> str:
    _typ(name, value, str)
    if not value or len(value) > MAX_ID_LEN or any(c in value for c in "/*$?# "):
        raise ProtocolError(f"{name}: bad identifier {value!r}")
    return value


def _vec(name: str, value: Any, n: int) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ProtocolError(f"{name}: expected a list of {n} numbers")
    out = np.array([_typ(f"{name}[{i}]", v, (int, float)) for i, v in enumerate(value)], dtype=np.float64)
    return out


def _check_transitions(m: dict) -> dict:
    _ident("actor", m.get("actor"))
    _typ("first_step", m.get("first_step"), int, low=0)
    arrays = {}
    n = None
    spec = {
        "obs": ("<f4", (None, OBS_DIM)),
        "next_obs": ("<f4", (None, OBS_DIM)),
        "action": ("<f4", (None, ACT_DIM)),
        "reward": ("<f4", (None,)),
        "terminated": ("|u1", (None,)),
        "truncated": ("|u1", (None,)),
        "intervened": ("|u1", (None,)),
        "clipped": ("|u1", (None,)),
    }
    for field_name, (dt, shape) in spec.items():
        arr = unpack_array(m.get(field_name), field_name, dtype=dt, shape=shape)
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise ProtocolError(f"{field_name}: {arr.shape[0]} rows, expected {n}")
        arrays[field_name] = arr
    if not 1 <= n <= MAX_BATCH:
        raise ProtocolError(f"batch of {n} transitions outside [1, {MAX_BATCH}]")
    if np.any(np.abs(arrays["action"]) > 1.0 + 1e-6):
        raise ProtocolError("actions outside [-1, 1]")
    for flag in ("terminated", "truncated", "intervened", "clipped"):
        if np.any(arrays[flag] > 1):
            raise ProtocolError(f"{flag}: flags must be 0/1")
    m.update(arrays)
    # optional (actor service): the oldest batch seq the actor still holds (everything below was confirmed
    # durable by a learner) and a random id per actor incarnation
    if "base_seq" in m:
        _typ("base_seq", m["base_seq"], int, low=0)
        if m["base_seq"] > m["seq"]:
            raise ProtocolError(f"base_seq {m['base_seq']} > seq {m['seq']}")
    if "stream" in m:
        _ident("stream", m["stream"])
    return m


def _check_ack(m: dict) -> dict:
    _ident("actor", m.get("actor"))
    for f in ("received", "durable"):
        _typ(f, m.get(f), int, low=-1)
    _typ("trained", m.get("trained"), int, low=0)
    _typ("epoch", m.get("epoch"), str)
    _typ("version", m.get("version"), int, low=0)  # latest weights version of this learner incarnation
    if "stream" in m:  # optional: the actor incarnation (transitions' stream) this ack is about
        _ident("stream", m["stream"])
    return m


def _check_weights(m: dict) -> dict:
    _typ("version", m.get("version"), int, low=0)
    if "epoch" in m:  # optional: the learner incarnation that made these weights (as in its acks)
        _ident("epoch", m["epoch"])
    _typ("trained", m.get("trained"), dict)
    for k, v in m["trained"].items():
        _ident("trained key", k)
        _typ(f"trained[{k}]", v, int, low=0)
    tensors = _typ("tensors", m.get("tensors"), dict)
    if not tensors or len(tensors) > 256:
        raise ProtocolError("tensors: expected 1..256 named arrays")
    out = {}
    for name, arr in tensors.items():
        _typ("tensor name", name, str)
        out[name] = unpack_array(arr, f"tensors[{name}]", dtype="<f4", shape=(None,) * len(arr.get("shape", []) if isinstance(arr, dict) else 0))
    m["tensors"] = out
    return m


def _check_correction(m: dict) -> dict:
    _ident("client", m.get("client"))
    _ident("actor", m.get("actor"))
    _typ("active", m.get("active"), bool)
    if m["active"]:
        m["p_h"] = _vec("p_h", m.get("p_h"), ACT_DIM)
    else:
        m["p_h"] = None
    if "episode" in m:
        _typ("episode", m["episode"], int, low=0)
    if "t" in m:
        _typ("t", m["t"], int, low=0)
    if "step" in m:  # optional: the actor step (of `episode`) this correction is for -- step-addressed
        _typ("step", m["step"], int, low=0)
        if "episode" not in m:
            raise ProtocolError("step: a step-addressed correction needs its episode")
    return m


def _check_frame(m: dict) -> dict:
    _ident("actor", m.get("actor"))
    _typ("episode", m.get("episode"), int, low=0)
    _typ("t", m.get("t"), int, low=0)
    _typ("phase", m.get("phase"), (int, float), low=0.0, high=1.0)
    for f in ("robot", "desired", "mean", "scale"):
        m[f] = _vec(f, m.get(f), ACT_DIM)
    _typ("intervening", m.get("intervening"), bool)
    _typ("scenario", m.get("scenario"), str)
    if "next_mean" in m:  # optional: the KMP mean at step t + 1 (absent after an episode's last step)
        m["next_mean"] = _vec("next_mean", m["next_mean"], ACT_DIM)
    return m


def _check_scale(m: dict) -> dict:
    _ident("actor", m.get("actor"))
    _typ("model", m.get("model"), dict)
    if "table" in m:
        m["table"] = unpack_array(m["table"], "table", dtype="<f8", shape=(None, ACT_DIM))
    return m


_EPISODE_NUMBERS = ("steps", "ret", "action_cost", "obstacle_cost", "passage_cost", "obstacle_steps", "interventions",
                    "intervention_steps", "clipped_steps", "projected_steps", "mean_abs_xi_h", "wall_time")


def _check_episode(m: dict) -> dict:
    _ident("actor", m.get("actor"))
    stats = _typ("stats", m.get("stats"), dict)
    _typ("episode", stats.get("episode"), int, low=1)
    for f in _EPISODE_NUMBERS:
        if f in stats:
            _typ(f"stats.{f}", stats[f], (int, float))
    for f in ("success", "failure"):
        if f in stats:
            _typ(f"stats.{f}", stats[f], bool)
    return m


def _check_status(m: dict) -> dict:
    _typ("role", m.get("role"), str)
    _typ("info", m.get("info"), dict)
    return m


def _check_control(m: dict) -> dict:
    _typ("command", m.get("command"), str)
    if m["command"] not in ("pause", "resume", "stop", "checkpoint"):
        raise ProtocolError(f"unknown command {m['command']!r}")
    return m


_CHECKS: dict[str, Callable[[dict], dict]] = {
    "transitions": _check_transitions,
    "ack": _check_ack,
    "weights": _check_weights,
    "correction": _check_correction,
    "frame": _check_frame,
    "scale": _check_scale,
    "episode": _check_episode,
    "status": _check_status,
    "control": _check_control,
}


def encode(kind: str, sender: str, seq: int, **fields: Any) -> bytes:
    """Pack one message; numpy arrays in ``fields`` become array maps (nested one level in dicts)."""
    if kind not in _CHECKS:
        raise ValueError(f"unknown message kind {kind!r}")
    msg = {"v": SCHEMA_VERSION, "kind": kind, "sender": sender, "seq": int(seq), "ts": time.time()}
    for k, v in fields.items():
        if isinstance(v, np.ndarray):
            v = pack_array(v)
        elif isinstance(v, dict):
            v = {kk: pack_array(vv) if isinstance(vv, np.ndarray) else vv for kk, vv in v.items()}
        msg[k] = v
    return msgpack.packb(msg, use_bin_type=True)


def decode(kind: str, payload: bytes) -> dict:
    """Unpack and validate a message of ``kind``; raises :class:`ProtocolError` with the reason."""
    limit = MAX_BYTES[kind]
    if not isinstance(payload, (bytes, bytearray)):
        raise ProtocolError("payload is not bytes")
    if len(payload) > limit:
        raise ProtocolError(f"{len(payload)} bytes exceeds the {kind} limit of {limit}")
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=limit, max_str_len=1 << 16,
                              max_array_len=1 << 16, max_map_len=1 << 12)
    except Exception as exc:  # msgpack raises several exception types for garbage
        raise ProtocolError(f"not msgpack: {type(exc).__name__}: {exc}") from None
    if not isinstance(msg, dict):
        raise ProtocolError("message is not a map")
    if msg.get("v") != SCHEMA_VERSION:
        raise ProtocolError(f"schema version {msg.get('v')!r}, expected {SCHEMA_VERSION}")
    if msg.get("kind") != kind:
        raise ProtocolError(f"kind {msg.get('kind')!r} on a {kind} topic")
    _ident("sender", msg.get("sender"))
    _typ("seq", msg.get("seq"), int, low=0)
    _typ("ts", msg.get("ts"), (int, float))
    try:
        return _CHECKS[kind](msg)
    except ProtocolError:
        raise
    except Exception as exc:  # a malformed field that slipped past a type check
        raise ProtocolError(f"malformed {kind}: {type(exc).__name__}: {exc}") from None


@dataclass
class RejectCounter:
    """Counts rejected messages by kind and reason; logs the first of each reason and then every 100th."""

    role: str

    def __post_init__(self) -> None:
        self.counts: Counter = Counter()
        self._lock = threading.Lock()

    def reject(self, kind: str, key: str, err: Exception) -> None:
        reason = str(err)[:160]  # each distinct reason is logged once, then every 100th message of the kind
        with self._lock:
            self.counts[kind] += 1
            n_kind = self.counts[kind]
            n_reason = self.counts[(kind, reason)] = self.counts[(kind, reason)] + 1
        if n_reason == 1 or n_kind % 100 == 0:
            log.warning("%s rejected %s message on %s (#%d of this kind): %s", self.role, kind, key, n_kind, err)

    @property
    def total(self) -> int:
        return sum(v for k, v in self.counts.items() if isinstance(k, str))

    def by_kind(self) -> dict[str, int]:
        return {k: v for k, v in self.counts.items() if isinstance(k, str)}
