"""Supervision in robot mode (README, "On a real robot"): the actor moves the robot only while it is sure that
somebody can stop it.

The run's supervisor -- ``khgrl up``, or ``khgrl supervise RUN_DIR`` for processes started by hand
(:mod:`khgrl.deploy.run.supervise`) -- publishes a heartbeat on ``control/actor`` every ``heartbeat_s``, which carries
the run's e-stop state (``heartbeat``: released, ``heartbeat-estop``: pressed). With supervision on (``--supervision``,
on in robot mode):

* before its first command the actor waits for a heartbeat (it cannot know the e-stop state without one);
* a ``heartbeat-estop`` latches the e-stop (one e-stop state for the run: an actor started or restarted after the
  press holds), except within ``supervision_timeout`` of a release (the supervisor's heartbeats sent before it heard
  the release);
* a heartbeat older than ``supervision_timeout`` -- the router killed or stopped, the supervisor gone, the network
  cut -- latches the e-stop: the robot holds at the next control step (no command but the task's ``hold``), and stays
  held when the heartbeat comes back, until the operator's ``khgrl stop --release``.

Without supervision (simulation mode by default) only the e-stop state file (``RUN_DIR/estop.json``,
:mod:`khgrl.common.delivery.estop_state`) is read at the start.
"""

from __future__ import annotations

from khgrl.common.wire.protocol import LAUNCHER

__all__ = ["Supervision", "heartbeat_refusal"]


def heartbeat_refusal(sender: str) -> str | None:
    """Why a heartbeat is refused (None: taken): only the operator's side (the launcher's identity) supervises.

    :param sender: the heartbeat's sender.
    """
    return None if sender == LAUNCHER else f"heartbeat from {sender!r}: only the launcher's side supervises the actors"


class Supervision:
    """The heartbeats the actor heard (module docstring).

    :param required: supervision is on (``safety.supervised(mode)``).
    :param timeout: ``supervision_timeout`` (s).
    """

    def __init__(self, required: bool, timeout: float) -> None:
        self.required, self.timeout = bool(required), float(timeout)
        self.last: float | None = None  # monotonic time of the last heartbeat
        self.released_at = -float("inf")  # monotonic time of the last release
        self.beats = 0

    def beat(self, now: float) -> None:
        """A heartbeat arrived.

        :param now: monotonic s.
        """
        self.last, self.beats = now, self.beats + 1

    @property
    def waiting(self) -> bool:
        """Supervision is on and no heartbeat came yet: the robot does not move."""
        return self.required and self.last is None

    def silence(self, now: float) -> float | None:
        """Seconds since the last heartbeat when that exceeds the timeout (the supervision is lost), else None.

        :param now: monotonic s.
        """
        if not self.required or self.last is None or now - self.last <= self.timeout:
            return None
        return now - self.last

    def stale_press(self, now: float) -> bool:
        """Whether a ``heartbeat-estop`` may predate the release just given (within the timeout of it).

        :param now: monotonic s.
        """
        return now - self.released_at <= self.timeout
