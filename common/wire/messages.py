"""One class per message kind of the wire protocol (docs/protocol.md). Each knows its kind, its size limit
and how to check a received map (``from_wire``); :mod:`khgrl.common.wire.protocol` does the envelope and msgpack.

Optional fields are ``None`` when absent (and are then left out of the payload).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from khgrl.common.wire.base import ANY_DIMS, MAC_BYTES, SIG_BYTES, Dims, Message, _any_vec, _mac, _sig, _vec
from khgrl.common.wire.batch import MAX_BATCH, Transitions
from khgrl.common.wire.checks import ProtocolError, ident, opt, typ, unpack_array, vec
from khgrl.common.wire.descriptor import MAX_DIM, MAX_HORIZON, TaskDescriptor
from khgrl.common.wire.status import _INFO, ActorInfo, HumanInfo, LearnerInfo, check_info

__all__ = ["Dims", "ANY_DIMS", "Message", "TaskInfo", "Transitions", "Ack", "Weights", "Correction", "Frame", "Scale",
           "EpisodeReport", "Status", "ActorInfo", "LearnerInfo", "HumanInfo", "Control", "MAX_BATCH", "COMMANDS",
           "MAC_BYTES", "SIG_BYTES"]

# e-stop; a person's ready; the supervisor's heartbeat (khgrl.common.wire.control: e-stop released / pressed)
COMMANDS = ("pause", "resume", "stop", "checkpoint", "estop", "release", "ready", "heartbeat", "heartbeat-estop")


@dataclass(frozen=True)
class Ack(Message):
    """What the learner holds of one actor's stream (docs/protocol.md, ``ack``)."""

    KIND: ClassVar[str] = "ack"
    actor: str
    received: int  # highest batch seq received without a gap (-1: none)
    durable: int  # highest seq held in a learner checkpoint
    trained: int  # this actor's transitions covered by the latest weights
    version: int  # latest weights version
    epoch: str  # random per learner incarnation
    stream: str | None = None  # the actor stream the ack is about
    task: str | None = None  # the digest of the learner's task descriptor
    superseded: bool | None = None  # true: the learner took another stream of this actor id; it refuses this one
    mac: bytes | None = None  # keyed BLAKE2b of the other fields under the run's key (khgrl.common.delivery.run_key)
    signer: str | None = None  # the key id that signed it (``learner:<id>``; khgrl.common.delivery.data_keys)
    sig: bytes | None = None  # its Ed25519 signature

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Ack":
        return cls(actor=ident("actor", m.get("actor")), received=typ("received", m.get("received"), int, low=-1),
                   durable=typ("durable", m.get("durable"), int, low=-1),
                   trained=typ("trained", m.get("trained"), int, low=0),
                   version=typ("version", m.get("version"), int, low=0), epoch=typ("epoch", m.get("epoch"), str),
                   stream=opt(m, "stream", ident), task=opt(m, "task", ident),
                   superseded=opt(m, "superseded", typ, bool), mac=opt(m, "mac", _mac),
                   signer=opt(m, "signer", ident), sig=opt(m, "sig", _sig))


@dataclass(frozen=True, eq=False)
class Weights(Message):
    """The TQC actor network's ``state_dict`` by version."""

    KIND: ClassVar[str] = "weights"
    MAX_BYTES: ClassVar[int] = 64 * 1024 * 1024
    version: int
    trained: dict  # {actor id: transitions covered}
    tensors: dict  # {name: float32 array}
    epoch: str | None = None
    mac: bytes | None = None  # keyed BLAKE2b of the other fields under the run's key (khgrl.common.delivery.run_key)
    signer: str | None = None  # the key id that signed it (``learner:<id>``; khgrl.common.delivery.data_keys)
    sig: bytes | None = None  # its Ed25519 signature

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Weights":
        trained = typ("trained", m.get("trained"), dict)
        for k, v in trained.items():
            ident("trained key", k)
            typ(f"trained[{k}]", v, int, low=0)
        tensors = typ("tensors", m.get("tensors"), dict)
        if not tensors or len(tensors) > 256:
            raise ProtocolError("tensors: expected 1..256 named arrays")
        out = {}
        for name, arr in tensors.items():
            typ("tensor name", name, str)
            ndim = len(arr.get("shape", [])) if isinstance(arr, dict) and isinstance(arr.get("shape"), list) else 0
            out[name] = unpack_array(arr, f"tensors[{name}]", dtype="<f4", shape=(None,) * ndim)
        return cls(version=typ("version", m.get("version"), int, low=0), trained=dict(trained), tensors=out,
                   epoch=opt(m, "epoch", ident), mac=opt(m, "mac", _mac), signer=opt(m, "signer", ident),
                   sig=opt(m, "sig", _sig))


@dataclass(frozen=True, eq=False)
class Correction(Message):
    """A human-input client's word for an actor: drag to ``p_h`` (active) or release."""

    KIND: ClassVar[str] = "correction"
    VECTORS: ClassVar[tuple[str, ...]] = ("p_h",)
    client: str
    actor: str
    active: bool
    p_h: np.ndarray | None = None  # (O,) command coordinates; required when active
    episode: int | None = None  # the frame reacted to (for the record)
    t: int | None = None
    step: int | None = None  # step-addressed: for this step of ``episode`` (lock-step)
    sig: bytes | None = None  # ``human:<client>``'s Ed25519 signature (khgrl.common.delivery.vouching)

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Correction":
        active = typ("active", m.get("active"), bool)
        step = opt(m, "step", typ, int, low=0)
        if step is not None and m.get("episode") is None:
            raise ProtocolError("step: a step-addressed correction needs its episode")
        return cls(client=ident("client", m.get("client")), actor=ident("actor", m.get("actor")), active=active,
                   p_h=_vec("p_h", m.get("p_h"), dims.out) if active else None,
                   episode=opt(m, "episode", typ, int, low=0), t=opt(m, "t", typ, int, low=0), step=step,
                   sig=opt(m, "sig", _sig))


@dataclass(frozen=True, eq=False)
class Frame(Message):
    """What an actor shows after each step (viewers and human-input clients draw and react to it)."""

    KIND: ClassVar[str] = "frame"
    VECTORS: ClassVar[tuple[str, ...]] = ("robot", "desired", "mean", "scale", "next_mean", "obs")
    MAX_BYTES: ClassVar[int] = 64 * 1024
    actor: str
    episode: int  # 1-based, counted over the whole run (a resumed run continues)
    t: int  # the step just taken, 0-based
    phase: float
    robot: np.ndarray
    desired: np.ndarray
    mean: np.ndarray
    scale: np.ndarray
    intervening: bool
    task: str  # the task's name
    ret: float | None = None
    next_mean: np.ndarray | None = None  # KMP mean at step t + 1; absent after the horizon's last step
    last: bool | None = None  # true on the episode's last frame (terminated or truncated)
    obs: np.ndarray | None = None  # the task environment's observation after the step (a scripted human may use it)
    # The episode's scene (issue 22), on the frame of t = 0 of a varying-scene task whose KMP was adapted only:
    scene_mean: np.ndarray | None = None  # (N, O) float64: the adapted KMP mean eta0 over the grid
    scene_projector: np.ndarray | None = None  # (N, O, O) float64: its null-space projector (the band's)
    scene_via: np.ndarray | None = None  # (V, 1 + O) float64: the via-points, [phase, position...] per row

    @property
    def has_scene(self) -> bool:
        """Whether the frame carries its episode's scene (any of the ``scene_*`` fields)."""
        return self.scene_mean is not None or self.scene_via is not None

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Frame":
        o = dims.out if dims.out is not None else len(_vec("robot", m.get("robot"), None))
        vecs = {f: vec(f, m.get(f), o) for f in ("robot", "desired", "mean", "scale")}
        t = typ("t", m.get("t"), int, low=0)
        return cls(actor=ident("actor", m.get("actor")), episode=typ("episode", m.get("episode"), int, low=0),
                   t=t, phase=float(typ("phase", m.get("phase"), (int, float), low=0.0, high=1.0)),
                   intervening=typ("intervening", m.get("intervening"), bool),
                   task=typ("task", m.get("task"), str), ret=opt(m, "ret", typ, (int, float)),
                   next_mean=opt(m, "next_mean", vec, o), last=opt(m, "last", typ, bool),
                   obs=opt(m, "obs", _any_vec, 4 * MAX_DIM), **_scene_fields(m, o, t, dims.horizon), **vecs)


MAX_FRAME_VIA = 16  # via-points a frame may carry (khgrl.common.tasks.scene.MAX_VIA_POINTS)


def _scene_fields(m: dict, o: int, t: int, horizon: int | None) -> dict:
    """A frame's ``scene_mean`` (N, O), ``scene_projector`` (N, O, O) and ``scene_via`` (V, 1 + O), checked: only on
    the frame of t = 0, float64, finite, N in [2, MAX_HORIZON] (= ``horizon`` where the receiver knows it), the
    projector only with the mean and on the same grid, 1..16 via-points with phases in [0, 1]."""
    names = ("scene_mean", "scene_projector", "scene_via")
    if all(m.get(k) is None for k in names):
        return {}
    if t != 0:
        raise ProtocolError(f"scene fields on the frame of t = {t}: they come only with an episode's first frame")
    mean = None
    if m.get("scene_mean") is not None:
        mean = unpack_array(m["scene_mean"], "scene_mean", dtype="<f8", shape=(horizon, o))
    if mean is not None and not 2 <= mean.shape[0] <= MAX_HORIZON:
        raise ProtocolError(f"scene_mean: {mean.shape[0]} grid points outside [2, {MAX_HORIZON}]")
    proj = None
    if m.get("scene_projector") is not None:
        if mean is None:
            raise ProtocolError("scene_projector without scene_mean")
        proj = unpack_array(m["scene_projector"], "scene_projector", dtype="<f8", shape=(mean.shape[0], o, o))
    via = None
    if m.get("scene_via") is not None:
        via = unpack_array(m["scene_via"], "scene_via", dtype="<f8", shape=(None, 1 + o))
        if not 1 <= via.shape[0] <= MAX_FRAME_VIA:
            raise ProtocolError(f"scene_via: {via.shape[0]} via-points outside [1, {MAX_FRAME_VIA}]")
        if np.any(via[:, 0] < 0.0) or np.any(via[:, 0] > 1.0):
            raise ProtocolError("scene_via: a phase outside [0, 1]")
    return {"scene_mean": mean, "scene_projector": proj, "scene_via": via}


@dataclass(frozen=True, eq=False)
class Scale(Message):
    """An actor's exploration-scale model after a refit, and its table of L over the KMP grid."""

    KIND: ClassVar[str] = "scale"
    MAX_BYTES: ClassVar[int] = 1024 * 1024
    actor: str
    model: dict  # ScaleModel.to_dict()
    table: np.ndarray | None = None  # (N, O) float64

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Scale":
        table = m.get("table")
        if table is not None:
            table = unpack_array(table, "table", dtype="<f8", shape=(None, dims.out))
            if not 1 <= table.shape[1] <= MAX_DIM:
                raise ProtocolError(f"table: {table.shape[1]} columns outside [1, {MAX_DIM}]")
        return cls(actor=ident("actor", m.get("actor")), model=typ("model", m.get("model"), dict),
                   table=table)


@dataclass(frozen=True, eq=False)
class TaskInfo(Message):
    """An actor's task descriptor (``task/actor/<id>``; the learner answers its own on ``task/learner/<id>``)."""

    KIND: ClassVar[str] = "task"
    MAX_BYTES: ClassVar[int] = 16 * 1024 * 1024
    sender_id: str
    descriptor: TaskDescriptor

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "TaskInfo":
        return cls(sender_id=ident("sender_id", m.get("sender_id")),
                   descriptor=TaskDescriptor.from_wire(m.get("descriptor")))


_STAT_NUMBERS = ("steps", "ret", "action_cost", "obstacle_cost", "passage_cost", "obstacle_steps", "interventions",
                 "intervention_steps", "clipped_steps", "projected_steps", "mean_abs_xi_h", "wall_time")


@dataclass(frozen=True)
class EpisodeReport(Message):
    """One finished episode's statistics (khgrl.common.metrics.EpisodeStats as a map)."""

    KIND: ClassVar[str] = "episode"
    MAX_BYTES: ClassVar[int] = 16 * 1024
    actor: str
    stats: dict

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "EpisodeReport":
        stats = typ("stats", m.get("stats"), dict)
        typ("stats.episode", stats.get("episode"), int, low=1)
        for f in _STAT_NUMBERS:
            opt(stats, f, lambda n, v: typ(f"stats.{n}", v, (int, float)))
        for f in ("success", "failure"):
            opt(stats, f, lambda n, v: typ(f"stats.{n}", v, bool))
        scale_max = stats.get("scale_max")
        if scale_max is not None:
            vec("stats.scale_max", scale_max, len(scale_max) if isinstance(scale_max, list) else -1)
        return cls(actor=ident("actor", m.get("actor")), stats=dict(stats))


@dataclass(frozen=True)
class Status(Message):
    """About once a second from every process: ``role`` and an ``info`` of that role's schema."""

    KIND: ClassVar[str] = "status"
    MAX_BYTES: ClassVar[int] = 16 * 1024
    role: str
    info: ActorInfo | LearnerInfo | HumanInfo

    def __post_init__(self) -> None:
        if self.role not in _INFO or not isinstance(self.info, _INFO[self.role]):
            raise ProtocolError(f"status of role {self.role!r} needs a {_INFO.get(self.role, ActorInfo).__name__}")

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Status":
        role = typ("role", m.get("role"), str)
        if role not in _INFO:
            raise ProtocolError(f"role {role!r} not one of {sorted(_INFO)}")
        return cls(role=role, info=check_info(_INFO[role], m.get("info"), "info"))


@dataclass(frozen=True)
class Control(Message):
    """``control/<target>``: pause, resume, stop, checkpoint, or the e-stop (``estop``, ``release``); ``signer`` and
    ``sig``: the signer's key id and its Ed25519 signature (khgrl.common.delivery.control_auth)."""

    KIND: ClassVar[str] = "control"
    command: str
    signer: str | None = None
    sig: bytes | None = None

    @classmethod
    def from_wire(cls, m: dict, dims: Dims = ANY_DIMS) -> "Control":
        command = typ("command", m.get("command"), str)
        if command not in COMMANDS:
            raise ProtocolError(f"unknown command {command!r}")
        return cls(command=command, signer=opt(m, "signer", ident), sig=opt(m, "sig", _sig))
