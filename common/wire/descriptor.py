"""The task descriptor: what every process needs to know of a run's task without importing its code.

An actor builds its task (:mod:`khgrl.common.tasks.world`) and announces the descriptor on
``khgrl/<run>/task/actor/<id>`` (a put at start and a queryable); the learner builds its spaces from it, the GUI
and monitors draw from it, a third-party client reads sizes from it. It is plain data (numbers, strings,
lists and two arrays), checked on receipt like every message (docs/protocol.md, ``task``).

``digest`` identifies the task: it hashes everything a learner and an actor must agree on (names, sizes,
bounds, constraints, horizon, L0, the demonstrations, the value bounds) but not the fitted KMP (mean and
projector), which a different BLAS may round differently. A learner and an actor whose digests differ refuse each
other.

Value bounds (what the learner accepts in a batch, :mod:`khgrl.common.wire.bounds`): ``reward_bound`` (|reward|
<= it) and the observation limits :attr:`TaskDescriptor.obs_limits` -- the observation space's bounds, each side
no further out than ``obs_bound`` (also where the space is unbounded), widened by :data:`OBS_MARGIN` of the width.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import asdict, dataclass, field, fields
from functools import cached_property
from typing import ClassVar

import numpy as np
from khgrl.common.wire.checks import ProtocolError, pack_array, typ, unpack_array

__all__ = ["TaskDescriptor", "MAX_DIM", "REWARD_BOUND", "OBS_BOUND", "MAX_BOUND", "OBS_MARGIN", "MAX_CAMERAS",
           "MAX_SIDE", "CHANNELS", "STATE", "CAMERA_NAME"]

MAX_DIM = 64
MAX_CONSTRAINTS = 1024
MAX_HORIZON = 100_000
REWARD_BOUND = 1e6  # default |reward| of a task's environment (khgrl.task.Task.reward_bound)
OBS_BOUND = 1e6  # default |observation| in every dimension, bounded by the space or not (Task.obs_bound)
MAX_BOUND = 1e12  # the largest bound a descriptor may carry: squares stay far below float32's 3.4e38
OBS_MARGIN = 0.1  # an observation may lie this fraction of its dimension's width (+ 1e-3) outside the space
MAX_CAMERAS = 4  # a camera task's images per observation (as khgrl.common.tasks.obs_spaces checks a task)
MAX_SIDE = 256  # pixels, height and width of one image
CHANNELS = (1, 3, 4)  # grey, RGB, RGBA
STATE = "state"  # the policy observation's key of the state vector (never a camera's name)
CAMERA_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]{0,31}$")


@dataclass(frozen=True, eq=False)
class TaskDescriptor:
    """A run's task as data.

    :param name: the task's name.
    :param spec: how it was selected (``passage:high_cov``, ``pkg.mod:make_task``).
    :param out_dim: O, the command (desired position) size = the policy's action size.
    :param obs_dim: the policy's observation size.
    :param obs_low: lower bounds of the policy's observation (-inf allowed as -1e30).
    :param obs_high: upper bounds.
    :param horizon: N, steps per episode (the KMP grid).
    :param workspace_low: the workspace box.
    :param workspace_high:
    :param G: hard constraints G P >= c (box rows first), (K, O).
    :param c: (K,).
    :param default_scale: L0 per output.
    :param learn_scale: KhGRL refits L from the human.
    :param axis_names: a name per output.
    :param view_axes: the two outputs of the main 2-D view.
    :param view_third: the output of the second view (-1: none).
    :param shapes: named objects to draw: {"kind": box|sphere|point, "name", and low/high, center/radius or at}.
    :param mean: (N, O) the KMP mean eta0 over the grid.
    :param demos: (M, N, O) the demonstrations.
    :param projector: (N, O, O) the KMP's null-space projector N_t on the grid (the exploration band a viewer
        draws is eta0 +- |N_t| L_t).
    :param reward_bound: the largest |reward| of a transition (the environment's bound plus the largest action
        cost the workspace allows).
    :param obs_bound: the largest |observation| in any dimension (where the space is unbounded, or wider).
    :param cameras: a camera task's images: name -> (H, W, C) uint8 (issue 37); the observation fields above then
        describe the policy observation's ``"state"`` vector. Empty for a vector task: then neither the wire map nor
        the digest has the field (a vector task's descriptor is byte for byte what it was before cameras).
    """

    name: str
    spec: str
    out_dim: int
    obs_dim: int
    obs_low: tuple[float, ...]
    obs_high: tuple[float, ...]
    horizon: int
    workspace_low: tuple[float, ...]
    workspace_high: tuple[float, ...]
    G: tuple[tuple[float, ...], ...]
    c: tuple[float, ...]
    default_scale: tuple[float, ...]
    learn_scale: bool
    axis_names: tuple[str, ...]
    view_axes: tuple[int, int]
    view_third: int
    shapes: tuple[dict, ...]
    mean: np.ndarray
    demos: np.ndarray
    projector: np.ndarray
    reward_bound: float = REWARD_BOUND
    obs_bound: float = OBS_BOUND
    cameras: dict[str, tuple[int, int, int]] = field(default_factory=dict)
    WIRE_OPTIONAL: ClassVar[tuple[str, ...]] = ("cameras",)  # on the wire and in the digest only when not empty

    @cached_property
    def obs_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) float64 arrays (obs_dim,): where an observation of this task may lie -- the space's bounds
        clipped to +-``obs_bound``, widened by :data:`OBS_MARGIN` of that width plus 1e-3 (an environment's
        rounding at its space's edge is not refused)."""
        low = np.clip(np.asarray(self.obs_low, np.float64), -self.obs_bound, self.obs_bound)
        high = np.clip(np.asarray(self.obs_high, np.float64), -self.obs_bound, self.obs_bound)
        margin = OBS_MARGIN * np.maximum(high - low, 0.0) + 1e-3
        return low - margin, high + margin

    @cached_property
    def digest(self) -> str:
        """16 hex characters identifying the task (see the module docstring); computed once (the learner checks it
        on every batch)."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("mean", "demos", "projector")}
        for name in self.WIRE_OPTIONAL:  # (a vector task's digest as before the field existed)
            if not d[name]:
                del d[name]
        text = json.dumps(d, sort_keys=True, default=list)
        h = hashlib.sha256(text.encode())
        h.update(np.ascontiguousarray(self.demos, dtype="<f8").tobytes())
        return h.hexdigest()[:16]

    @property
    def third(self) -> int | None:
        return None if self.view_third < 0 else self.view_third

    def to_wire(self) -> dict:
        """The descriptor as a map for msgpack (arrays as array maps)."""
        arrays = ("mean", "demos", "projector")
        d = {k: _lists(v) for k, v in asdict(self).items() if k not in arrays}
        for name in self.WIRE_OPTIONAL:
            if not d[name]:
                del d[name]
        d.update({k: pack_array(np.asarray(getattr(self, k), "<f8")) for k in arrays})
        return d

    @classmethod
    def from_wire(cls, m: dict) -> "TaskDescriptor":
        """Check a received map; raises :class:`ProtocolError` saying what is wrong."""
        m = typ("task", m, dict)
        o = typ("out_dim", m.get("out_dim"), int, low=1, high=MAX_DIM)
        n_obs = typ("obs_dim", m.get("obs_dim"), int, low=1, high=4 * MAX_DIM)
        n = typ("horizon", m.get("horizon"), int, low=2, high=MAX_HORIZON)
        g = _rows("G", m.get("G"), o)
        names = typ("axis_names", m.get("axis_names"), list)
        if len(names) != o or not all(isinstance(s, str) and 0 < len(s) <= 32 for s in names):
            raise ProtocolError(f"axis_names: expected {o} short strings")
        axes = _ints("view_axes", m.get("view_axes"), 2, o)
        third = typ("view_third", m.get("view_third"), int, low=-1, high=o - 1)
        shapes = typ("shapes", m.get("shapes"), list)
        if len(shapes) > 64:
            raise ProtocolError("shapes: at most 64")
        return cls(name=_text("name", m.get("name")), spec=_text("spec", m.get("spec"), 200), out_dim=o,
                   obs_dim=n_obs, obs_low=_floats("obs_low", m.get("obs_low"), n_obs, finite=False),
                   obs_high=_floats("obs_high", m.get("obs_high"), n_obs, finite=False), horizon=n,
                   workspace_low=_floats("workspace_low", m.get("workspace_low"), o),
                   workspace_high=_floats("workspace_high", m.get("workspace_high"), o), G=g,
                   c=_floats("c", m.get("c"), len(g)),
                   default_scale=_floats("default_scale", m.get("default_scale"), o),
                   learn_scale=typ("learn_scale", m.get("learn_scale"), bool), axis_names=tuple(names),
                   view_axes=(axes[0], axes[1]), view_third=third,
                   shapes=tuple(_shape(s, o) for s in shapes),
                   mean=unpack_array(m.get("mean"), "mean", dtype="<f8", shape=(n, o)),
                   demos=unpack_array(m.get("demos"), "demos", dtype="<f8", shape=(None, n, o)),
                   projector=unpack_array(m.get("projector"), "projector", dtype="<f8", shape=(n, o, o)),
                   reward_bound=_bound("reward_bound", m.get("reward_bound")),
                   obs_bound=_bound("obs_bound", m.get("obs_bound")), cameras=_cameras(m.get("cameras")))


def _cameras(v) -> dict[str, tuple[int, int, int]]:
    """The ``cameras`` map, checked: at most :data:`MAX_CAMERAS` names (ident-like, not ``state``), each [H, W, C]
    with 1 <= H, W <= :data:`MAX_SIDE` and C in :data:`CHANNELS`; absent: none (a vector task)."""
    if v is None:
        return {}
    if not isinstance(v, dict) or not 1 <= len(v) <= MAX_CAMERAS:
        raise ProtocolError(f"cameras: expected a map of 1..{MAX_CAMERAS} cameras")
    out = {}
    for name, shape in v.items():
        if not isinstance(name, str) or not CAMERA_NAME.match(name) or name == STATE:
            raise ProtocolError(f"cameras: name {name!r} is not a short identifier other than {STATE!r}")
        if not isinstance(shape, list) or len(shape) != 3 or not all(type(d) is int for d in shape):
            raise ProtocolError(f"cameras[{name}]: expected [H, W, C] integers, got {shape!r}")
        h, w, c = shape
        if not (1 <= h <= MAX_SIDE and 1 <= w <= MAX_SIDE) or c not in CHANNELS:
            raise ProtocolError(f"cameras[{name}]: shape {shape}: at most {MAX_SIDE} x {MAX_SIDE}, C in {CHANNELS}")
        out[name] = (h, w, c)
    return out


def _lists(v):
    """Tuples as lists, recursively (what msgpack gives a receiver)."""
    if isinstance(v, (tuple, list)):
        return [_lists(x) for x in v]
    if isinstance(v, dict):
        return {k: _lists(x) for k, x in v.items()}
    return v


def _text(name: str, v, limit: int = 64) -> str:
    v = typ(name, v, str)
    if not 0 < len(v) <= limit:
        raise ProtocolError(f"{name}: 1..{limit} characters")
    return v


def _floats(name: str, v, n: int, finite: bool = True) -> tuple[float, ...]:
    if not isinstance(v, list) or len(v) != n:
        raise ProtocolError(f"{name}: expected a list of {n} numbers")
    out = []
    for i, x in enumerate(v):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or np.isnan(x) or (finite and not np.isfinite(x)):
            raise ProtocolError(f"{name}[{i}]: expected a {'finite ' if finite else ''}number")
        out.append(float(x))
    return tuple(out)


def _bound(name: str, v) -> float:
    """A value bound: a number in (0, MAX_BOUND]."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_BOUND:
        raise ProtocolError(f"{name}: expected a number in (0, {MAX_BOUND:g}]")
    return float(v)


def _ints(name: str, v, n: int, bound: int) -> tuple[int, ...]:
    if not isinstance(v, list) or len(v) != n:
        raise ProtocolError(f"{name}: expected a list of {n} integers")
    return tuple(typ(f"{name}[{i}]", x, int, low=0, high=bound - 1) for i, x in enumerate(v))


def _rows(name: str, v, o: int) -> tuple[tuple[float, ...], ...]:
    if not isinstance(v, list) or len(v) > MAX_CONSTRAINTS:
        raise ProtocolError(f"{name}: expected a list of at most {MAX_CONSTRAINTS} rows")
    return tuple(_floats(f"{name}[{k}]", row, o) for k, row in enumerate(v))


def _shape(s, o: int) -> dict:
    s = typ("shape", s, dict)
    kind = typ("shape.kind", s.get("kind"), str)
    coords = {"box": ("low", "high"), "sphere": ("center",), "point": ("at",)}.get(kind)
    if coords is None:
        raise ProtocolError(f"shape.kind {kind!r} not box, sphere or point")
    out: dict = {"kind": kind, "name": _text("shape.name", s.get("name"))}
    for c in coords:
        out[c] = _floats(f"shape.{c}", s.get(c), o)
    if kind == "sphere":
        out["radius"] = float(typ("shape.radius", s.get("radius"), (int, float), low=0.0))
    extra = set(s) - set(out)
    if extra:
        raise ProtocolError(f"shape: unknown fields {sorted(extra)}")
    return out
