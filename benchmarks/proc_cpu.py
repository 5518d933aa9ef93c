"""CPU seconds of a process tree by role, read from ``/proc`` (Linux): what a benchmark's case cost its processes
over a window (``khgrl bench images``: the router, the learner and the actors, with and without shared memory).

A process's role is read from its command line: ``router``, ``learner``, ``actor``, or ``other`` (the launcher,
human clients). Processes that exited inside the window are missing from its end: measure while the tree runs.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["ROLES", "tree_cpu", "cpu_between"]

ROLES = ("router", "learner", "actor")
_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _stat(pid: str) -> tuple[int, float] | None:
    """(parent pid, CPU seconds: user + system) of ``pid``; None if it is gone or unreadable."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rfind(")") + 2:].split()  # after "pid (comm) ": state, ppid, ..., utime (12th), stime
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / _TICK


def _role(pid: int) -> str:
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return "other"
    words = {a.decode(errors="replace") for a in argv[1:6]}
    return next((r for r in ROLES if r in words or f"khgrl.{r}.main" in words), "other")


def tree_cpu(root: int) -> dict[int, tuple[str, float]]:
    """Every process under ``root`` (itself included): pid -> (role, CPU seconds so far).

    :param root: the pid at the top of the tree (e.g. ``khgrl up``)
    """
    stats = {int(p): s for p in os.listdir("/proc") if p.isdigit() and (s := _stat(p)) is not None}
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    out, todo = {}, [root]
    while todo:
        pid = todo.pop()
        if pid in stats:
            out[pid] = (_role(pid), stats[pid][1])
            todo += children.get(pid, [])
    return out


def cpu_between(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]]) -> dict[str, float]:
    """CPU seconds each role spent between two :func:`tree_cpu` readings (a process new in ``after`` counts whole).

    :param before: the earlier reading
    :param after: the later one
    """
    spent = dict.fromkeys((*ROLES, "other"), 0.0)
    for pid, (role, cpu) in after.items():
        spent[role] += cpu - before.get(pid, (role, 0.0))[1]
    return {k: round(v, 2) for k, v in spent.items()}
