"""The ``info`` schemas of ``status`` messages (:class:`khgrl.common.wire.messages.Status`), one dataclass per role,
and the
check of a received info map against its schema."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, get_type_hints

from khgrl.common.wire.checks import ProtocolError, typ

__all__ = ["ActorInfo", "LearnerInfo", "HumanInfo", "check_info"]

_COUNTS = dict[str, int]


def check_info(cls, info: Any, where: str):
    """A status info map checked against the dataclass ``cls``: every field present with its type (ints,
    floats, bools, strings, optional floats, and {str: int} maps); unknown fields rejected."""
    info = typ(where, info, dict)
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    extra = set(info) - names
    if extra:
        raise ProtocolError(f"{where}: unknown fields {sorted(extra)}")
    kw = {}
    for f in dataclasses.fields(cls):
        if f.name not in info:
            raise ProtocolError(f"{where}.{f.name}: missing")
        v, t, name = info[f.name], hints[f.name], f"{where}.{f.name}"
        if t == _COUNTS:
            typ(name, v, dict)
            for k, n in v.items():
                typ(f"{name} key", k, str)
                typ(f"{name}[{k}]", n, int)
        elif t == (float | None):
            if v is not None:
                typ(name, v, (int, float))
        else:
            typ(name, v, (int, float) if t is float else t)
        kw[f.name] = v
    return cls(**kw)


@dataclass(frozen=True)
class ActorInfo:
    """``status/actor/<id>``: the actor's stream, flow control and corrections."""

    id: str
    episode: int
    t: int
    transitions: int
    sent: int
    next_seq: int
    outbox: int
    received: int
    durable: int
    trained: int
    weights_version: int
    ack_version: int
    learner_alive: bool
    waits: int
    wait_s: float
    resends: int
    corrections: _COUNTS
    intervening: bool
    rejects: _COUNTS
    paused: bool
    period_ms_p50: float | None
    alarm: str = ""  # another process publishes as this actor, or two learners run: in one line ("" when neither)
    held: str = ""  # why the robot is held now ("" when it is not): the e-stop, a pause, the learner, a silent human
    safety: _COUNTS = dataclasses.field(default_factory=dict)  # the watchdog's counts (actor/safety.py)


@dataclass(frozen=True)
class LearnerInfo:
    """``status/learner/<id>``: ingest, training, weights and checkpoints."""

    id: str
    epoch: str
    ingested: int
    iterations: int
    gradient_steps: int
    grad_steps_per_s: float
    version: int
    pending_iterations: int
    queue_depth: int
    rejects: _COUNTS
    paused: bool
    checkpoints: int
    next_seq: _COUNTS
    durable: _COUNTS
    duplicates: _COUNTS
    weights_queries: int
    checkpoint_error: str = ""  # why the last checkpoint save failed (a disk fault); "" when it succeeded
    checkpoint_failures: int = 0  # failed checkpoint saves of this learner process
    mode: str = "simulation"  # StreamSettings.mode: simulation (actors wait) or robot (they never do)
    utd: float = 0.0  # update-to-data ratio achieved: gradient steps per transition ingested after learning_starts
    rss_mb: float = 0.0  # the learner process's resident memory
    not_admitted_dropped: int = 0  # batches of actor ids not admitted yet, dropped over the inbox's caps (re-sent)
    rollbacks: int = 0  # training iterations rolled back: a loss or parameter went non-finite
    prior_fraction: float = 0.0  # share of a minibatch from the prior (intervened) slots: 0 uniform, 0.5 RLPD's
    prior_slots: int = 0  # stored transitions with intervened = 1 (the prior data: interventions, demonstrations)
    sampled_prior: int = 0  # transitions sampled from the prior slots (RLPD's half), all minibatches so far
    sampled_online: int = 0  # and uniformly from all slots
    alarm: str = ""  # two different batches signed by one actor for one (stream, seq): a split brain ("" when none)


@dataclass(frozen=True)
class HumanInfo:
    """``status/human/<id>``: a human-input client's traffic."""

    frames: int
    corrections: int
    rejects: _COUNTS


_INFO = {"actor": ActorInfo, "learner": LearnerInfo, "human": HumanInfo}


