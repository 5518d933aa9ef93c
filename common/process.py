"""What every KhGRL process does the same way: stop on SIGINT/SIGTERM through a flag, die with its launcher,
and log to its run directory."""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
from pathlib import Path

__all__ = ["StopFlag", "install_stop_handlers", "die_with_parent", "setup_process_logging", "PARENT_ENV"]

PARENT_ENV = "KHGRL_PARENT_PID"  # set by khgrl.deploy.run.supervisor for the processes it starts
_PR_SET_PDEATHSIG = 1


class StopFlag:
    """Set by SIGINT/SIGTERM (or a stop command); long loops poll it and leave their ``with`` blocks cleanly."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reason = ""

    def set(self, reason: str = "stop") -> None:
        self.reason = self.reason or reason
        self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float) -> bool:
        return self.event.wait(timeout)


def install_stop_handlers(flag: StopFlag) -> None:
    """SIGINT and SIGTERM set ``flag``; a second one exits at once."""

    def handler(signum, _frame):
        if flag:
            sys.stderr.write(f"second {signal.Signals(signum).name}: exiting now\n")
            os._exit(128 + signum)
        flag.set(signal.Signals(signum).name)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def die_with_parent() -> None:
    """If a supervisor started this process (``KHGRL_PARENT_PID``), ask Linux to send it SIGTERM when that
    parent dies -- even by SIGKILL -- so that no child outlives its launcher; exit at once if the parent is
    already gone. Elsewhere (not Linux, or started by hand) nothing happens."""
    parent = os.environ.get(PARENT_ENV)
    if not parent or not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        return
    if os.getppid() != int(parent):  # the parent died before prctl took effect
        os._exit(1)


def setup_process_logging(log_path: str | Path) -> None:
    """Log INFO and above to ``log_path`` and stdout (the launcher captures stdout in RUN_DIR/logs/)."""
    fmt = logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s")
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    Path(log_path).parent.mkdir(parents=True, exist_ok=True)
    for h in (logging.FileHandler(Path(log_path)), logging.StreamHandler(sys.stdout)):
        h.setFormatter(fmt)
        root.addHandler(h)
