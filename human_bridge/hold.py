"""The hold on one actor's desired position that every human client shares (the GUI's drag, the keyboard's and the
gamepad's velocity hold; docs/protocol.md, ``correction``). No Zenoh, no pygame.

A hold starts with one ``active`` correction sent at once (:meth:`CorrectionHold.start`); while it is on, P_h may
move (:meth:`CorrectionHold.move`, sent with the next frame or keepalive), one ``active`` correction answers every
frame of the driven actor, and one goes at least every :data:`KEEPALIVE_S` when no frame comes (e.g. the actor is
paused: :meth:`CorrectionHold.keepalive`). It ends with one release: when the person lets go, when the driven actor
changes, or with its episode -- on the episode's last frame (``last``), or on a frame of a later episode (the last
one was missed). A correction carries the (episode, t) of the driven actor's latest frame.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
from khgrl.common.wire.messages import Frame

__all__ = ["CorrectionHold", "KEEPALIVE_S"]

KEEPALIVE_S = 0.1  # while held, send at least this often even without frames


class CorrectionHold:
    """One client's hold on the driven actor's desired position P_h (see the module docstring).

    :param send: ``send(actor, p_h or None, episode, t)`` publishes one correction
        (:meth:`khgrl.human_bridge.client.CorrectionPublisher.send`).
    :param actor: the actor driven (None: none yet; :meth:`drive` sets it).
    :param clock: the time source of the keepalive (seconds).
    """

    def __init__(self, send: Callable, actor: str | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.send, self.actor, self.clock = send, actor, clock
        self.frame: Frame | None = None  # the driven actor's latest frame
        self.p_h: np.ndarray | None = None
        self.episode: int | None = None  # the episode the hold started in (None: started before any frame)
        self.sent = 0
        self.holds = 0
        self.last_send = 0.0

    @property
    def holding(self) -> bool:
        """Whether a hold is on (P_h is sent)."""
        return self.p_h is not None

    def drive(self, actor: str | None, frame: Frame | None = None) -> None:
        """Drive ``actor`` from now on (its latest ``frame`` if known), releasing what was held before."""
        self.release()
        if actor != self.actor:
            self.actor, self.frame = actor, frame

    def offer(self, frame: Frame) -> bool:
        """A frame of the driven actor (others are ignored): remember it; while holding, answer it, or release if
        its episode ended. True when this frame ended the hold with its episode.

        :param frame: a decoded frame.
        """
        if frame.actor != self.actor:
            return False
        self.frame = frame
        if not self.holding:
            return False
        if frame.last or (self.episode is not None and frame.episode != self.episode):
            self.release()
            return True
        self._send(self.p_h)
        return False

    def start(self, p_h: np.ndarray | None) -> bool:
        """Start a hold at ``p_h`` (sent at once); False (nothing sent) without an actor or a point."""
        if self.actor is None or p_h is None:
            return False
        self.p_h = np.asarray(p_h, np.float64).copy()
        self.episode = None if self.frame is None else self.frame.episode
        self.holds += 1
        self._send(self.p_h)
        return True

    def move(self, p_h: np.ndarray | None) -> None:
        """While holding, P_h moves to ``p_h`` (sent with the next frame or keepalive; None keeps it)."""
        if self.holding and p_h is not None:
            self.p_h = np.asarray(p_h, np.float64).copy()

    def release(self) -> None:
        """End the hold with one release (nothing when not holding)."""
        if self.holding:
            self.p_h = None
            self._send(None)

    def keepalive(self) -> None:
        """While held, re-send P_h if nothing was sent for :data:`KEEPALIVE_S`."""
        if self.holding and self.clock() - self.last_send >= KEEPALIVE_S:
            self._send(self.p_h)

    def _send(self, p_h: np.ndarray | None) -> None:
        f = self.frame
        ep, t = (f.episode, f.t) if f is not None else (0, 0)
        self.send(self.actor, None if p_h is None else p_h.copy(), ep, t)
        self.sent += 1
        self.last_send = self.clock()
