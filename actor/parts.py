"""The pieces the actor's loop drives (:mod:`khgrl.actor.loop`), built and wired by :mod:`khgrl.actor.main`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from khgrl.actor.arbiter import CorrectionArbiter
from khgrl.actor.exploration import ExplorationScale
from khgrl.actor.physical import PhysicalHands
from khgrl.actor.record import CorrectionRecord
from khgrl.actor.results import EpisodeLog
from khgrl.actor.telemetry import TensorBoard
from khgrl.actor.weights import PolicyWeights
from khgrl.common.delivery.actor_link import ActorLink
from khgrl.common.delivery.control_auth import ControlGate
from khgrl.common.delivery.stream import TransitionStream
from khgrl.common.delivery.transport import Inbox
from khgrl.common.step_records import StepRecord
from khgrl.common.wire.checks import RejectCounter

__all__ = ["ActorParts"]


@dataclass
class ActorParts:
    """The pieces the loop drives: the task and policy, the delivery layer's link, inbox and transition stream, the
    correction arbiter, the policy weights, the exploration scale and the result files (``steps``: every step of
    each finished episode, :mod:`khgrl.common.step_records`, and any live viewer listening to them)."""

    env: Any  # khgrl.common.tasks.kgrl_env.KGRLEnv (the task behind the KGRL mapping)
    policy: Any  # sb3_contrib TQCPolicy
    link: ActorLink
    inbox: Inbox
    stream: TransitionStream
    arbiter: CorrectionArbiter
    weights: PolicyWeights
    scale: ExplorationScale
    record: CorrectionRecord
    episodes: EpisodeLog
    tensorboard: TensorBoard
    rejects: RejectCounter
    task: Any = None  # khgrl.common.wire.descriptor.TaskDescriptor this actor announced
    announcer: Any = None  # khgrl.common.delivery.task_link.TaskAnnouncer
    physical: PhysicalHands = field(default_factory=PhysicalHands.off)  # --physical (off: does nothing)
    steps: StepRecord = field(default_factory=lambda: StepRecord(None))  # steps/episode-N.npz (None: nothing)
    control: ControlGate = field(default_factory=lambda: ControlGate.of_run(None))  # who may send control
