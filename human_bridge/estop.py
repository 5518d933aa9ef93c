"""A human-input client's e-stop (x in a window, a device's e-stop button): one press is repeated every
:data:`REPEAT_S` until the actors' statuses confirm it, as ``khgrl stop --now`` does -- a press while the router
restarts is not lost. Every actor whose status the client heard in the last :data:`FRESH_S` must say, in a status
that came after the press, that it is held by the e-stop with this client among those who pressed it (an e-stop the
watchdog latched on a lost link is not this press: the client goes on until its own is named). Any admitted client
may press it, for every actor; only the operator releases it (``khgrl stop RUN_DIR --release``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

__all__ = ["EStopPress", "REPEAT_S", "FRESH_S"]

log = logging.getLogger("khgrl.human")

REPEAT_S = 0.25  # the press again, while not confirmed
FRESH_S = 5.0  # an actor whose status came within this long counts as one that must confirm


class EStopPress:
    """The client's e-stop press and its confirmation.

    :param send: publishes one ``estop`` request.
    :param by: how the actors name this client's press (``human client <id>``): a status confirms it only when it
        names it -- an e-stop already latched by another (the watchdog on a lost link) is not this press (default:
        any e-stop confirms)
    """

    def __init__(self, send: Callable[[], None], by: str = "") -> None:
        self.send, self.by = send, by
        self.since: float | None = None  # when the unconfirmed press began (None: none waits)
        self.confirmed_after: float | None = None  # seconds from the press to its confirmation
        self.presses = 0
        self._last = -float("inf")
        self._held: dict[str, tuple[float, str]] = {}  # actor -> (when its status came, its held)
        self._lock = threading.Lock()

    def on_status(self, sample) -> None:
        """An actor's status (a Zenoh thread)."""
        from khgrl.common.wire.messages import Status
        from khgrl.common.wire.protocol import ProtocolError, decode

        try:
            st = decode(Status, sample.payload.to_bytes())
        except ProtocolError:
            return
        if st.role == "actor":
            with self._lock:
                self._held[st.info.id] = (time.monotonic(), st.info.held)

    def press(self) -> None:
        """The e-stop key: send now, and again until confirmed."""
        self.since, self.confirmed_after = time.monotonic(), None
        self._send()

    def _send(self) -> None:
        self._last = time.monotonic()
        self.presses += 1
        try:
            self.send()
        except Exception as exc:  # noqa: BLE001 - no router now: sent again in REPEAT_S
            log.warning("e-stop not sent (sent again in %.2f s): %s", REPEAT_S, exc)

    @property
    def confirmed(self) -> bool:
        """Whether every actor heard recently confirmed the press (False while none was heard)."""
        now, since = time.monotonic(), self.since
        with self._lock:
            recent = {a: v for a, v in self._held.items() if now - v[0] <= FRESH_S}
        return since is not None and bool(recent) and all(t >= since and self._names_us(held)
                                                          for t, held in recent.values())

    def _names_us(self, held: str) -> bool:
        """Whether an actor's held reason is the e-stop with this client's press among its pressers ("e-stop by A (also
        pressed by B, C)", :meth:`khgrl.actor.inbound.Inbound.held_reason`)."""
        if not held.startswith("e-stop by "):
            return False
        names = held[len("e-stop by "):].replace(" (also pressed by ", ", ").rstrip(")").split(", ")
        return not self.by or self.by in names

    def tick(self) -> None:
        """Called each pass of the client's loop: repeat the press until confirmed."""
        if self.since is None:
            return
        if self.confirmed:
            self.confirmed_after = time.monotonic() - self.since
            log.warning("e-stop confirmed by the actors %.2f s after the press (%d sent)", self.confirmed_after,
                        self.presses)
            self.since = None
        elif time.monotonic() - self._last >= REPEAT_S:
            self._send()
