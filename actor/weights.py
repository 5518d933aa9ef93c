"""The actor's copy of the policy weights: receive the learner's ``weights`` messages in a background
thread, validate them against the local actor network, admit them by learner epoch and version (a
:class:`~khgrl.common.delivery.trust.WeightsGate`, when one is installed: the control loop installs it), and swap them
into the
policy between steps (a ``load_state_dict``, no stall). Also counts how far the loaded weights lag behind the
transitions taken.

One module of ~310 lines on purpose: receiving, checking and loading the learner's weights: one path from the wire
to the policy.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
from khgrl.common.delivery.trust import WeightsGate
from khgrl.common.wire.checks import ProtocolError, RejectCounter
from khgrl.common.wire.messages import Weights
from khgrl.common.wire.protocol import decode

__all__ = ["WeightsUpdate", "WeightsReceiver", "PolicyWeights", "expected_bytes", "WEIGHTS_SLACK"]

log = logging.getLogger("khgrl.actor")

# Bytes a weights message may have beyond its tensors' data: the envelope, names, shapes and the ``trained`` map
# (at most 4,096 actor ids of up to 64 characters). A larger message cannot be this network's: refused before decoding.
WEIGHTS_SLACK = 512 * 1024


def expected_bytes(template: dict[str, tuple]) -> int:
    """The encoded size of a weights message for a network of these tensor shapes, without the slack: float32 data
    plus each tensor's map (name, dtype, shape).

    :param template: tensor shapes by name.
    """
    return sum(4 * int(np.prod(shape, dtype=np.int64)) + 48 + len(name.encode()) + 9 * len(shape)
               for name, shape in template.items())


@dataclass(frozen=True)
class WeightsUpdate:
    """One validated weights message, ready to load.

    :param epoch: the learner incarnation that trained them.
    :param version: weights version (per epoch).
    :param trained: {actor id: transitions covered}.
    :param state_dict: tensors by name, matching the actor network.
    :param ts: when the learner published them (its clock).
    """

    epoch: str | None
    version: int
    trained: dict
    state_dict: dict
    ts: float


class WeightsReceiver:
    """Drains a RingChannel(1) weights subscriber in a background thread: decodes, validates names and shapes
    against the local actor network, converts to tensors and leaves the newest ready for the control loop.

    :param subscriber: the newest weights payload
        (:meth:`~khgrl.common.delivery.actor_link.ActorLink.weights_subscriber`; None: only :meth:`parse` is used).
    :param template: the actor network's tensors by name (their shapes, or tensors: what to expect; the policy's
        :meth:`~khgrl.learner.algorithm.ActorPolicy.weights_template`).
    :param rejects: counts refused weights messages.
    :param key: the weights key (for the reject log).
    :param gate: admits weights by learner epoch and version (None: every well-formed message; see
        :meth:`use_gate`).
    """

    def __init__(self, subscriber, template: dict, rejects: RejectCounter, key: str,
                 gate: WeightsGate | None = None) -> None:
        self.sub = subscriber
        self.template = {k: tuple(getattr(v, "shape", v)) for k, v in template.items()}
        self.max_bytes = expected_bytes(self.template) + WEIGHTS_SLACK
        self.rejects = rejects
        self.key = key
        self.lock = threading.Lock()
        self.ready: WeightsUpdate | None = None
        self.received = 0  # messages admitted
        self.gate = gate
        self.thread = threading.Thread(target=self._run, name="weights-rx", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        while True:
            try:
                payload = self.sub.recv()
            except Exception:  # noqa: BLE001 - ZError "channel is empty and closed" after undeclare
                return
            self.offer(payload)

    def parse(self, payload) -> WeightsUpdate:
        """Decode and check one weights payload (raises :class:`ProtocolError`): first its length against the size
        of this network's weights (before anything is copied or decoded), then the message, then the tensors'
        names and shapes (the data is still a view of the payload), then (with the run's key) the learner's ``mac``,
        and only then the copy into tensors.

        :param payload: the encoded message (bytes, or Zenoh's ZBytes: copied only once its length fits).
        """
        import torch

        if len(payload) > self.max_bytes:
            raise ProtocolError(f"{len(payload)} bytes: the actor network's weights take at most {self.max_bytes} "
                                f"(refused before decoding)")
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            payload = payload.to_bytes()
        msg = decode(Weights, payload)
        tensors = msg.tensors
        if set(tensors) != set(self.template):
            raise ProtocolError(f"tensors: names {sorted(tensors)} do not match the actor network")
        for k, shape in self.template.items():
            if tuple(tensors[k].shape) != shape:
                raise ProtocolError(f"tensors[{k}]: shape {tensors[k].shape}, the actor network has {shape}")
        if self.gate is not None:
            self.gate.authentic(msg)  # with the run's key: the learner's mac (hashing costs more than the checks above)
        sd = {k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in tensors.items()}
        return WeightsUpdate(msg.epoch, msg.version, dict(msg.trained), sd, float(msg.envelope.ts))

    def offer(self, payload: bytes) -> None:
        """Parse ``payload`` and, if the gate admits it, keep it as the newest ready update (a refused one is
        counted as rejected; one the gate holds may come out of :meth:`learner_appeared`).

        :param payload: the encoded message.
        """
        try:
            item = self.parse(payload)
        except ProtocolError as exc:
            self.rejects.reject("weights", self.key, exc)
            return
        with self.lock:
            if self._admit(item):
                self.ready = item

    def admit(self, item: WeightsUpdate) -> bool:
        """Whether the gate lets ``item`` be loaded now (refused ones are counted; held ones kept by the gate).

        :param item: a parsed update.
        """
        with self.lock:
            return self._admit(item)

    def _admit(self, item: WeightsUpdate) -> bool:
        ok = True
        if self.gate is not None:
            try:
                ok = self.gate.admit(item)
            except ProtocolError as exc:
                self.rejects.reject("weights", self.key, exc)
                ok = False
            self._count_dropped()
        self.received += ok
        return ok

    def _count_dropped(self) -> None:
        for why in self.gate.take_dropped():
            self.rejects.reject("weights", self.key, ProtocolError(why))

    def use_gate(self, gate: WeightsGate) -> None:
        """Admit by ``gate`` from now on (an update already waiting is checked again).

        :param gate: the actor's weights gate.
        """
        with self.lock:
            self.gate = gate
            item, self.ready = self.ready, None
            if item is not None:
                self.received -= 1
                if self._admit(item):
                    self.ready = item

    def learner_appeared(self, key: str) -> None:
        """A learner's liveliness token appeared: follow its epoch; held weights of it become ready.

        :param key: the liveliness key.
        """
        if self.gate is None:
            return
        with self.lock:
            item = self.gate.learner_appeared(key)
            self._count_dropped()
            if item is not None and self.ready is None:  # (weights that came since, of a learner followed, go first)
                self.received += 1
                self.ready = item

    def learner_gone(self, key: str) -> None:
        """A learner's liveliness token disappeared: its weights are held from now on.

        :param key: the liveliness key.
        """
        if self.gate is not None:
            self.gate.learner_gone(key)

    def take(self) -> WeightsUpdate | None:
        """The newest update not yet taken (None: nothing new); drops held weights whose learner never came."""
        with self.lock:
            if self.gate is not None:
                self.gate.expire()
                self._count_dropped()
            item, self.ready = self.ready, None
        return item

    def stop(self) -> None:
        if self.sub is not None:
            try:
                self.sub.undeclare()
            except Exception:  # noqa: BLE001
                pass
        if self.thread.is_alive():
            self.thread.join(timeout=2.0)


class PolicyWeights:
    """Which weights the policy runs with, and how they lag behind the transitions taken.

    :param policy: the local policy (:class:`~khgrl.learner.algorithm.ActorPolicy`: ``load_weights`` takes the
        state dicts).
    :param actor: this actor's id (its entry in ``trained``).
    :param receiver: the background receiver to take updates from.
    """

    def __init__(self, policy, actor: str, receiver: WeightsReceiver) -> None:
        self.policy = policy
        self.actor = actor
        self.receiver = receiver
        self.epoch: str | None = None
        self.version = -1
        self.trained = 0  # this actor's transitions the loaded weights were trained on
        self.initial_version: int | None = None
        self.swaps = 0
        self.latency: list[float] = []  # s from the learner's publish (msg ts) to applied in the loop
        self.max_lag = 0
        self.lag_hist: dict[str, int] = {}  # steps by (transitions - those the loaded weights were trained on)
        self.last_query = -1e9  # when the loop last asked the learner's queryable (time.monotonic())

    def load(self, item: WeightsUpdate) -> bool:
        """Load ``item`` unless it is not newer than what runs (and what runs is plausible); returns whether it was
        loaded.

        :param item: a parsed update (admitted by the receiver's gate).
        """
        if item.epoch == self.epoch and item.version <= self.version:
            gate = self.receiver.gate
            why = None if gate is None else gate.implausible(self.epoch, self.version)
            if why is None:
                return False
            log.warning("replacing the loaded weights with version %d: %s", item.version, why)
        self.policy.load_weights(item.state_dict)
        self.epoch, self.version = item.epoch, item.version
        self.trained = int(item.trained.get(self.actor, 0))
        self.swaps += 1
        return True

    def swap(self) -> None:
        """Load the receiver's newest update, if any (between steps)."""
        item = self.receiver.take()
        if item is not None and self.load(item):  # applied: latency from the learner's publish (same-machine clock)
            self.latency.append(time.time() - item.ts)

    def load_replies(self, payloads: list[bytes]) -> None:
        """Load the answers of the learner's weights queryable (late joiner / missed update).

        :param payloads: the reply payloads.
        """
        for p in payloads:
            try:
                item = self.receiver.parse(p)
            except ProtocolError as exc:
                self.receiver.rejects.reject("weights", self.receiver.key, exc)
                continue
            if self.receiver.admit(item):
                self.load(item)

    def behind(self, ack_epoch: str | None, ack_version: int) -> bool:
        """Whether the learner has newer weights than the loaded ones (per its last ack).

        :param ack_epoch: the learner epoch of the last ack (None: no ack yet).
        :param ack_version: the weights version of the last ack.
        """
        if ack_epoch is None:
            return False
        if self.epoch is not None and self.epoch != ack_epoch:
            return True
        return self.version < ack_version

    def note_lag(self, transitions: int, max_lead: int) -> None:
        """Count the lag of a policy step: transitions taken minus those the loaded weights were trained on.

        :param transitions: this actor's transitions so far.
        :param max_lead: the flow-control lead (the histogram's last bin is ``>= 2 * max_lead``).
        """
        lag = transitions - self.trained
        self.max_lag = max(self.max_lag, lag)
        b = str(lag) if lag < 2 * max_lead else f">={2 * max_lead}"
        self.lag_hist[b] = self.lag_hist.get(b, 0) + 1

    def summary(self) -> dict:
        """This part of ``summary.json``: ``weights`` and ``weights_latency_ms``."""
        wl = np.asarray(self.latency)

        def ms(v) -> float | None:
            return float(v * 1e3) if wl.size else None

        return {
            "weights": {"initial_version": self.initial_version, "final_version": self.version, "swaps": self.swaps,
                        "received": self.receiver.received, "max_lag": self.max_lag,
                        "lag_histogram": dict(sorted(self.lag_hist.items(), key=lambda kv: (len(kv[0]), kv[0])))},
            "weights_latency_ms": {"p50": ms(np.percentile(wl, 50)) if wl.size else None,
                                   "p99": ms(np.percentile(wl, 99)) if wl.size else None,
                                   "max": ms(wl.max()) if wl.size else None, "n": int(wl.size)},
        }
