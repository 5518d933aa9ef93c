"""benchmarks/proc_cpu.py: a process tree's CPU seconds by role, read from /proc (``khgrl bench images``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from helpers import wait_for

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")

# a child whose argv names the router role: burns 0.5 CPU-s once told to (a line on the stdin it shares with its
# parent), then waits to be killed
BURN = ("import sys, time\nsys.stdin.readline()\nt = time.process_time()\n"
        "while time.process_time() - t < 0.5: pass\ntime.sleep(30)")
PARENT = f"import subprocess, sys, time\nsubprocess.Popen([sys.executable, '-c', {BURN!r}, 'router'])\ntime.sleep(30)"


def _router(tree: dict) -> float:
    return sum(cpu for role, cpu in tree.values() if role == "router")


def test_a_trees_cpu_by_role_counts_its_children():
    from khgrl.benchmarks.proc_cpu import cpu_between, tree_cpu

    def reading(done):
        tree = tree_cpu(p.pid)
        return tree if done(tree) else None

    p = subprocess.Popen([sys.executable, "-c", PARENT], stdin=subprocess.PIPE, text=True)
    try:
        before = wait_for(lambda: reading(lambda t: len(t) == 2), 30, "the child")
        p.stdin.write("burn\n")
        p.stdin.flush()
        after = wait_for(lambda: reading(lambda t: _router(t) >= _router(before) + 0.5), 30, "its burn")
    finally:
        for pid in tree_cpu(p.pid):
            os.kill(pid, signal.SIGKILL)
        p.wait()
    assert sorted(role for role, _ in after.values()) == ["other", "router"], after  # the parent has no role
    spent = cpu_between(before, after)
    assert 0.5 <= spent["router"] <= 0.7 and spent["other"] < 0.1, spent
    assert spent["learner"] == spent["actor"] == 0.0
