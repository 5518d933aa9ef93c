"""Disk faults of a learner's saves (a full, read-only or unwritable directory, an I/O error): which errors are
the disk's (:func:`is_disk_fault`) rather than a bug, a short reason for the status (:func:`fault_reason`), and
:class:`SaveFaults`, which counts the failed checkpoints and journal writes, logs them (not every retry) and says
when to retry (exponential backoff). A failed save leaves the previous checkpoint as it was
(:mod:`khgrl.learner.checkpoint`); the learner trains and ingests on, and the actors keep what is not durable.
"""

from __future__ import annotations

import errno
import logging
import math
import time
from typing import Callable

__all__ = ["SaveFaults", "is_disk_fault", "fault_reason", "RETRY_FIRST_S", "RETRY_MAX_S"]

log = logging.getLogger("khgrl.learner")

RETRY_FIRST_S = 1.0  # a failed save is retried after 1 s, 2 s, 4 s, ... up to RETRY_MAX_S
RETRY_MAX_S = 30.0
WARN_EVERY_S = 60.0  # a failure with an unchanged reason is logged again at most this often
MAX_REASON = 300  # characters of a failure's reason kept (status messages carry it)


def is_disk_fault(exc: BaseException) -> bool:
    """Whether a failed save is a fault of the disk (full, read-only, unwritable, I/O error), which a learner
    survives and retries, rather than a bug.

    :param exc: what :func:`save_checkpoint` raised
    """
    if isinstance(exc, OSError):
        return True
    return isinstance(exc, RuntimeError) and "write" in str(exc).lower()  # torch: "... failed writing file ..."


def fault_reason(exc: BaseException) -> str:
    """A short reason for a failed save: ``ENOSPC No space left on device: PATH``.

    :param exc: the error
    """
    if isinstance(exc, OSError) and exc.errno is not None:
        text = f"{errno.errorcode.get(exc.errno, f'errno {exc.errno}')} {exc.strerror or ''}".strip()
        if exc.filename:
            text += f": {exc.filename}"
    else:
        text = f"{type(exc).__name__}: {exc}"
    return text[:MAX_REASON]


class SaveFaults:
    """The checkpoint saves of one learner process that failed: the last reason (empty once one succeeds), the
    failures, when to retry (after RETRY_FIRST_S, doubling up to RETRY_MAX_S), and log lines that say so
    (a failure once per reason or WARN_EVERY_S, the recovery once).

    :param clock: monotonic seconds
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.error = ""  # why the last save failed; "" when it succeeded
        self.failures = 0  # failed saves in this process
        self.streak = 0  # failed saves since the last success
        self.retry_at = 0.0  # no save before this (clock)
        self._since = 0.0
        self._warned_at = -math.inf

    def ready(self) -> bool:
        """Whether a save may be tried now (always, unless a failed one waits out its backoff)."""
        return self.clock() >= self.retry_at

    def failed(self, exc: BaseException, unsaved: int, what: str = "checkpoint") -> float:
        """A save failed: note it, log it (rate-limited), and return the seconds until the retry.

        :param exc: the disk fault
        :param unsaved: transitions accepted that no checkpoint or journal holds (not durable)
        :param what: what failed ('checkpoint', 'model checkpoint', 'journal write')
        """
        now, reason = self.clock(), fault_reason(exc)
        if self.streak == 0:
            self._since = now
        delay = min(RETRY_MAX_S, RETRY_FIRST_S * 2 ** min(self.streak, 16))
        self.streak += 1
        self.failures += 1
        self.retry_at = now + delay
        if reason != self.error or now - self._warned_at >= WARN_EVERY_S:
            self._warned_at = now
            log.warning("%s failed (%s); %d failed attempts in %.0f s; training and ingest go on, %d "
                        "transitions are not durable and the actors keep them until a checkpoint holds them; "
                        "retrying in %.0f s (then at most every %.0f s)", what, reason, self.streak, now - self._since,
                        unsaved, delay, RETRY_MAX_S)
        self.error = reason
        return delay

    def succeeded(self) -> None:
        """A save succeeded (logs the recovery after failures)."""
        if self.streak:
            log.warning("checkpoint recovered after %d failed attempts over %.0f s (last: %s)", self.streak,
                        self.clock() - self._since, self.error)
        self.error, self.streak, self.retry_at = "", 0, 0.0
