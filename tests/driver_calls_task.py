"""The passage world (``passage:low_cov``) behind a robot driver that logs every call it gets: the task's ``command``
adapter (a position sent to the robot) and its ``hold`` adapter (the actor holds it) append a line each to the file
``$KHGRL_DRIVER_LOG`` -- ``command <time.time()> <pid>`` or ``hold <time.time()> <pid>`` -- so a test can count the
commands the robot got after a fault, across processes and restarts (tests/integration/test_supervision.py).

A module of its own: the tests put ``tests/`` on the processes' ``PYTHONPATH`` and give ``--task
driver_calls_task:make_task`` as a user gives their task.
"""

from __future__ import annotations

import os
import time
from dataclasses import replace

from khgrl.common.tasks.api import Task, load_task

__all__ = ["make_task", "read_log"]


def _log(kind: str) -> None:
    path = os.environ.get("KHGRL_DRIVER_LOG")
    if path:
        with open(path, "a") as fh:  # (O_APPEND: one line per write, whichever process)
            fh.write(f"{kind} {time.time():.6f} {os.getpid()}\n")


def _command(env, p_t):
    _log("command")
    return p_t


def _hold(env, p_t) -> None:
    _log("hold")


def make_task() -> Task:
    """``passage:low_cov`` with the logging driver's adapters."""
    return replace(load_task("passage:low_cov"), command=_command, hold=_hold)


def read_log(path) -> list[tuple[str, float, int]]:
    """The driver's calls: (kind, time, pid), in the order written.

    :param path: the log file.
    """
    out = []
    try:
        text = open(path).read()
    except FileNotFoundError:
        return out
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 3:
            out.append((parts[0], float(parts[1]), int(parts[2])))
    return out
