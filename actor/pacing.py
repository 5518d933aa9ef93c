"""Timing of the control loop: pace steps to ``--rate`` with perf_counter deadlines, measure the loop
period, and optionally run the loop thread under SCHED_FIFO (:func:`set_realtime`)."""

from __future__ import annotations

import logging
import os
import time

__all__ = ["Pacer", "set_realtime"]

log = logging.getLogger("khgrl.actor")


class Pacer:
    """Deadlines every ``1 / rate`` s; a loop that fell behind by more than a period does not try to catch up.

    :param rate: control rate in Hz (0: free-running, :meth:`sleep` never sleeps).
    """

    def __init__(self, rate: float) -> None:
        self.period = 1.0 / rate if rate > 0 else 0.0
        self.deadline = time.perf_counter()
        self.last_start: float | None = None
        self.late = 0.0  # how late (s) the last deadline :meth:`sleep` waited for had passed (0: on time)
        self.periods: list[float] = []  # s between the starts of consecutive steps

    def sleep(self) -> bool:
        """Wait for the next deadline; returns whether it slept (then what arrived meanwhile is due)."""
        if self.period <= 0:
            return False
        self.deadline += self.period
        now = time.perf_counter()
        self.late = max(0.0, now - self.deadline)
        if self.deadline < now - self.period:  # fell behind by more than a period: don't try to catch up
            self.deadline = now
        elif self.deadline > now:
            time.sleep(self.deadline - now)
            return True
        return False

    def resync(self) -> None:
        """The loop held on purpose (a pause, the e-stop, a wait): the next deadline is now, not a late one, and the
        time held is not a loop period."""
        self.deadline = time.perf_counter() - self.period
        self.last_start = None

    def step_started(self) -> None:
        """A step starts now: record the period since the last one."""
        start = time.perf_counter()
        if self.last_start is not None:
            self.periods.append(start - self.last_start)
        self.last_start = start


def set_realtime(priority: int) -> bool:
    """Run the calling thread -- the control loop; Zenoh's, the weights receiver's and TensorBoard's threads are
    already started and keep the normal policy -- under SCHED_FIFO at ``priority`` (1-99), as robot control
    loops are run, so that CPU-bound neighbours (a learner on the same machine) do not delay its wake-ups.
    Linux only, needs CAP_SYS_NICE (root); without it, logs why and returns False (the loop runs as before).
    The loop sleeps every period (``--rate`` is required), so it cannot starve the machine.

    :param priority: SCHED_FIFO priority, 1-99.
    """
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:
        log.warning("could not run the control loop under SCHED_FIFO %d (%s): normal scheduling", priority, exc)
        return False
    log.info("control loop thread runs under SCHED_FIFO priority %d", priority)
    return True
