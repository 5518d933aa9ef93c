"""What bounds a human-input client's power over an actor (docs/protocol.md, "Limits on human clients"): which
actors it is assigned to (:class:`Assignments`), how long it may hold one (:class:`HoldAllowance`), how long its pause
lasts unless renewed (:class:`HumanPauses`), and how far outside the workspace its P_h may lie (:func:`far_outside`).

Pure logic, no Zenoh: the correction arbiter (:mod:`khgrl.actor.arbiter`) and the actor's inbound handler
(:mod:`khgrl.actor.inbound`) use them.
"""

from __future__ import annotations

import logging

import numpy as np
from khgrl.common.config.settings import parse_assignments

__all__ = ["Assignments", "HoldAllowance", "HumanPauses", "far_outside", "parse_assignments", "FAR_MARGIN",
           "MAX_CLIENTS"]

log = logging.getLogger("khgrl.actor")

FAR_MARGIN = 0.1  # P_h more than this fraction of the workspace's extent outside it (on any axis) is refused
MAX_CLIENTS = 64  # clients whose allowance or pause is remembered (the oldest entry is forgotten first)


class Assignments:
    """Which clients may correct or pause this actor.

    :param actor: this actor's id.
    :param spec: the ``human_clients`` setting (:func:`parse_assignments`; "": every client).
    """

    def __init__(self, actor: str, spec: str = "") -> None:
        self.actor = actor
        self.table = parse_assignments(spec)

    def allows(self, client: str) -> bool:
        """Whether ``client`` is assigned to this actor.

        :param client: the client's id.
        """
        if self.table is None:
            return True
        ids = self.table.get(client, frozenset())
        return "*" in ids or self.actor in ids


def far_outside(p_h: np.ndarray, low: np.ndarray, high: np.ndarray, margin: float = FAR_MARGIN) -> str | None:
    """Why ``p_h`` is too far outside the workspace box to be projected onto it (None: it is not): more than
    ``margin`` times the box's extent outside it on some axis.

    :param p_h: the correction's P_h.
    :param low: the workspace's lower corner.
    :param high: the workspace's upper corner.
    :param margin: the allowed distance outside, as a fraction of the extent per axis.
    """
    slack = margin * (high - low)
    bad = np.flatnonzero((p_h < low - slack) | (p_h > high + slack))
    if not bad.size:
        return None
    i = int(bad[0])
    return (f"P_h[{i}] = {float(p_h[i]):.6g} is more than {margin:.0%} of the workspace's extent outside "
            f"[{float(low[i]):.6g}, {float(high[i]):.6g}]: refused, not projected")


class HoldAllowance:
    """Each client's allowance of holding time on this actor, in seconds of the actor's running time (waits for the
    learner and pauses do not count): it starts full at ``capacity``, a hold spends it one second per second, and it
    refills at ``refill`` seconds per second while the client does not hold, up to ``capacity``. A hold whose
    allowance runs out is released, and that client may start a new one only once its allowance is back to a quarter
    of ``capacity``. So one client holds at most ``capacity`` seconds at a stretch and, over a long run, at most
    ``refill / (1 + refill)`` of the actor's running time.

    :param capacity: the allowance when full (s; 0 or less: unlimited).
    :param refill: seconds regained per second not holding.
    """

    def __init__(self, capacity: float, refill: float) -> None:
        self.capacity, self.refill = float(capacity), float(refill)
        self._left: dict[str, tuple[float, float]] = {}  # client -> (allowance, running time it was computed at)

    @property
    def unlimited(self) -> bool:
        return self.capacity <= 0

    def left(self, client: str, now: float) -> float:
        """The allowance of ``client`` at running time ``now`` (refilled since it last held).

        :param client: the client's id.
        :param now: the actor's running time (s).
        """
        if self.unlimited or client not in self._left:
            return self.capacity
        amount, since = self._left[client]
        return min(self.capacity, amount + self.refill * max(0.0, now - since))

    def may_start(self, client: str, now: float) -> bool:
        """Whether ``client`` may start a hold now (its allowance is at least a quarter of the capacity).

        :param client: the client's id.
        :param now: the actor's running time (s).
        """
        return self.unlimited or self.left(client, now) >= 0.25 * self.capacity

    def spend(self, client: str, seconds: float, now: float) -> float:
        """``client`` held for the last ``seconds`` (up to ``now``); returns what is left.

        :param client: the holder.
        :param seconds: running time it held.
        :param now: the actor's running time (s).
        """
        if self.unlimited:
            return self.capacity
        amount, since = self._left.get(client, (self.capacity, now))
        amount = min(self.capacity, amount + self.refill * max(0.0, now - seconds - since)) - seconds
        self._left.pop(client, None)
        if len(self._left) >= MAX_CLIENTS:
            self._left.pop(next(iter(self._left)))
        self._left[client] = (max(0.0, amount), now)
        return max(0.0, amount)


class HumanPauses:
    """The pauses human-input clients asked for (``pause`` on ``human/<client>/request``), each until its client's
    ``resume`` or ``limit`` seconds after it was last asked for (a client renews a pause by asking again).

    :param limit: seconds a pause lasts unless renewed (0 or less: until resumed).
    """

    def __init__(self, limit: float) -> None:
        self.limit = float(limit)
        self._until: dict[str, float] = {}  # client -> when its pause ends
        self.expired = 0

    def pause(self, client: str, now: float) -> None:
        """``client`` asks for (or renews) a pause.

        :param client: the client's id.
        :param now: ``time.monotonic()``.
        """
        self._until.pop(client, None)
        if len(self._until) >= MAX_CLIENTS:
            self._until.pop(next(iter(self._until)))
        self._until[client] = now + self.limit if self.limit > 0 else float("inf")

    def holds(self, client: str) -> bool:
        """Whether ``client`` has a pause on record (expired or not).

        :param client: the client's id.
        """
        return client in self._until

    def resume(self, client: str) -> None:
        """``client`` lifts its own pause.

        :param client: the client's id.
        """
        self._until.pop(client, None)

    def active(self, now: float) -> bool:
        """Whether a client's pause holds the actor now (expired ones are dropped, counted and logged).

        :param now: ``time.monotonic()``.
        """
        for client in [c for c, t in self._until.items() if t <= now]:
            del self._until[client]
            self.expired += 1
            log.warning("pause of human-input client %r expired: not renewed within %.0f s", client, self.limit)
        return bool(self._until)
