"""Which weights the actor may load, checked without access control (docs/protocol.md, ``weights`` and ``ack``):
only weights of a learner incarnation whose liveliness token is alive, with versions that move forward plausibly.

A learner announces its incarnation (``epoch``) in its liveliness token ``alive/learner/<id>/<epoch>``.
:class:`WeightsGate` keeps the epochs whose tokens are alive now and, per epoch, how high a version can be by now.
A learner makes one weights version per training iteration, and no learner does more than
:data:`MAX_VERSIONS_PER_S` iterations a second (one iteration is ``gradient_steps`` TQC gradient steps on a batch of
256; the fastest measured is well under a thousand a second, even with one gradient step per iteration on a GPU).
So after version ``v`` of an epoch was seen (in an ack or in weights) at time ``t``, no genuine message of that epoch
carries more than ``v + VERSION_SLACK + MAX_VERSIONS_PER_S * (now - t)``. The gate keeps the lowest such ceiling
over everything it has seen, so a forged high version loosens nothing once a genuine message has been seen (and a
forged version 10**9 would need almost 6 days to become plausible). The first version seen of an epoch cannot be
checked (there is nothing earlier to compare it with); weights loaded then are replaced as soon as a genuine lower
version shows them implausible (:meth:`WeightsGate.implausible`).

Weights of an epoch whose token has not been seen are *held*, the newest one only, and released when that token
appears (a learner publishes version 0 just before it declares its token). A held message is dropped (reported in
:meth:`WeightsGate.take_dropped`, which the receiver counts as refused) when one of another epoch takes its place or
after :data:`HOLD_S`. Weights without an epoch are refused while a learner with an epoch is alive (and taken only
from a learner whose token has no epoch chunk).

With the run's key (:mod:`~khgrl.common.delivery.run_key`), weights without the learner's ``mac`` are refused
(:meth:`WeightsGate.authentic`, checked as they are parsed, before anything is copied), and the epochs noted
(:attr:`WeightsGate.vouched`) are those of signed messages only.

Pure logic, no Zenoh: the weights receiver's thread and the control loop both call it (it locks).
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

from khgrl.common.delivery import data_keys
from khgrl.common.wire.checks import ProtocolError

__all__ = ["WeightsGate", "learner_of", "MAX_VERSIONS_PER_S", "VERSION_SLACK", "HOLD_S", "MAX_EPOCHS"]

MAX_VERSIONS_PER_S = 2000.0  # training iterations (= weights versions) a learner can make per second, at most
VERSION_SLACK = 1000  # versions allowed above the last one seen at once (acks and weights overtake each other)
HOLD_S = 10.0  # weights of an epoch whose token has not appeared are dropped after this long
MAX_EPOCHS = 16  # epochs whose versions are remembered (the oldest is forgotten first)


def learner_of(key: str) -> tuple[str, str | None] | None:
    """``(learner id, epoch)`` of a learner liveliness key ``khgrl/<run>/alive/learner/<id>[/<epoch>]`` (epoch
    None: a token without the epoch chunk); None if the key is not one.

    :param key: a liveliness key expression.
    """
    parts = str(key).split("/")
    if len(parts) not in (5, 6) or parts[2:4] != ["alive", "learner"] or not all(parts[4:]):
        return None
    return parts[4], (parts[5] if len(parts) == 6 else None)


class WeightsGate:
    """Admits weights by the epochs alive and the versions seen (see the module's docstring).

    :param clock: monotonic seconds.
    :param rate: versions per second a learner can make at most.
    :param slack: versions allowed above the last seen at once.
    :param hold_s: seconds a held message waits for its learner's token.
    :param key: the run's key (weights must carry the learner's ``mac``; None: not checked).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, *, rate: float = MAX_VERSIONS_PER_S,
                 slack: int = VERSION_SLACK, hold_s: float = HOLD_S, key: data_keys.Keyish = None) -> None:
        self.clock, self.rate, self.slack, self.hold_s = clock, float(rate), int(slack), float(hold_s)
        self.key = key
        self.alive: dict[str, str | None] = {}  # liveliness key -> its epoch
        self._floor: dict[str | None, float] = {}  # epoch -> min(version - rate * time) over the versions seen
        self._held: tuple[Any, float] | None = None  # (weights of an epoch not alive, when they came)
        self._dropped: list[str] = []
        self._lock = threading.RLock()

    @property
    def epochs(self) -> set[str | None]:
        """The epochs of the learners alive now."""
        with self._lock:
            return set(self.alive.values())

    def alive_now(self) -> dict[str, str | None]:
        """The learner tokens followed now: liveliness key -> epoch (a copy)."""
        with self._lock:
            return dict(self.alive)

    @property
    def vouched(self) -> set[str | None]:
        """The epochs of the messages taken so far (weights admitted, acks noted; with the key: signed ones)."""
        with self._lock:
            return set(self._floor)

    def authentic(self, msg: Any) -> None:
        """Raise :class:`ProtocolError` if ``msg`` (a decoded weights message) lacks the learner's ``mac`` under the
        run's key (nothing is checked without one).

        :param msg: a :class:`~khgrl.common.wire.messages.Weights`.
        """
        why = data_keys.check(msg, self.key)
        if why:
            raise ProtocolError(why)

    # ------------------------------------------------------------------ learners
    def learner_appeared(self, key: str) -> Any | None:
        """A learner's token appeared: its epoch is followed from now on. Returns the held weights of that epoch,
        if any and still plausible, to be loaded (the gate forgets them).

        :param key: the liveliness key.
        """
        who = learner_of(key)
        if who is None:
            return None
        with self._lock:
            self.alive[key] = who[1]
            if self._held is None or self._held[0].epoch != who[1]:
                return None
            item, self._held = self._held[0], None
            why = self.implausible(item.epoch, item.version)
            if why:
                self._dropped.append(why)
                return None
            self.note(item.epoch, item.version)
            return item

    def learner_gone(self, key: str) -> None:
        """A learner's token disappeared.

        :param key: the liveliness key.
        """
        with self._lock:
            self.alive.pop(key, None)

    # ------------------------------------------------------------------ versions
    def ceiling(self, epoch: str | None) -> float | None:
        """The highest version of ``epoch`` a genuine message can carry now (None: none of it seen yet).

        :param epoch: a learner epoch.
        """
        with self._lock:
            floor = self._floor.get(epoch)
        return None if floor is None else floor + self.slack + self.rate * self.clock()

    def implausible(self, epoch: str | None, version: int) -> str | None:
        """Why ``version`` of ``epoch`` cannot be genuine now (None: it can).

        :param epoch: a learner epoch.
        :param version: a weights version (of weights or an ack).
        """
        top = self.ceiling(epoch)
        if top is None or version <= top:
            return None
        return (f"version {version} of learner epoch {epoch} is implausible: at most {int(top)} by now (a learner "
                f"makes at most {self.rate:.0f} versions a second)")

    def note(self, epoch: str | None, version: int) -> None:
        """A version of ``epoch`` seen in a message taken (an ack, or weights admitted).

        :param epoch: a learner epoch.
        :param version: its weights version.
        """
        floor = version - self.rate * self.clock()
        with self._lock:
            if epoch not in self._floor and len(self._floor) >= MAX_EPOCHS:
                self._floor.pop(next(iter(self._floor)))
            self._floor[epoch] = min(self._floor.get(epoch, floor), floor)

    # ------------------------------------------------------------------ weights
    def admit(self, item: Any) -> bool:
        """Whether weights (anything with ``epoch`` and ``version``) may be loaded now: True (their version is
        noted), False (held until their learner's token appears); raises :class:`ProtocolError` if refused.

        :param item: a parsed weights message.
        """
        with self._lock:
            epochs = set(self.alive.values())
            if item.epoch is None and any(e is not None for e in epochs):
                followed = sorted(e for e in epochs if e)
                raise ProtocolError(f"weights without an epoch, while learner epoch(s) {followed} are followed")
            if item.epoch not in epochs:
                self._hold(item)
                return False
            why = self.implausible(item.epoch, item.version)
            if why:
                raise ProtocolError(why)
            self.note(item.epoch, item.version)
            return True

    def _hold(self, item: Any) -> None:
        held = self._held
        if held is not None and held[0].epoch != item.epoch:
            self._dropped.append(self._unclaimed(held[0], "weights of another epoch came"))
        self._held = (item, self.clock())

    @staticmethod
    def _unclaimed(item: Any, why: str) -> str:
        return (f"weights version {item.version} of learner epoch {item.epoch}: no learner of that epoch appeared "
                f"({why})")

    def expire(self) -> None:
        """Drop held weights that have waited :attr:`hold_s` for their learner's token."""
        with self._lock:
            if self._held is not None and self.clock() - self._held[1] > self.hold_s:
                self._dropped.append(self._unclaimed(self._held[0], f"held {self.hold_s:.0f} s"))
                self._held = None

    @property
    def held(self) -> Any | None:
        """The weights held now (None: none)."""
        with self._lock:
            return None if self._held is None else self._held[0]

    def take_dropped(self) -> list[str]:
        """Why each held message dropped since the last call was dropped (to count them as refused)."""
        with self._lock:
            out, self._dropped = self._dropped, []
        return out
