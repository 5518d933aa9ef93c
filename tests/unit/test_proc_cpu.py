"""benchmarks/proc_cpu.py: a process tree's CPU seconds by role, read from /proc (``khgrl bench images``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from helpers import wait_for

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")

# a child whose argv names the router role: burns 0.6 CPU-s once the file in its argv exists, then waits to be killed
BURN = ("import os, sys, time\nwhile not os.path.exists(sys.argv[1]): time.sleep(0.01)\nt = time.process_time()\n"
        "while time.process_time() - t < 0.6: pass\ntime.sleep(30)")
PARENT = ("import subprocess, sys, time\n"
          f"subprocess.Popen([sys.executable, '-c', {BURN!r}, sys.argv[1], 'router'])\ntime.sleep(30)")


def _router(tree: dict) -> float:
    return sum(cpu for role, cpu in tree.values() if role == "router")


def test_a_trees_cpu_by_role_counts_its_children(tmp_path):
    from khgrl.benchmarks.proc_cpu import cpu_between, tree_cpu

    def reading(done):
        tree = tree_cpu(p.pid)
        return tree if done(tree) else None

    go = tmp_path / "go"
    p = subprocess.Popen([sys.executable, "-c", PARENT, str(go)])
    try:
        before = wait_for(lambda: reading(lambda t: len(t) == 2 and _router(t) > 0), 30, "the child")
        go.touch()
        after = wait_for(lambda: reading(lambda t: _router(t) >= _router(before) + 0.5), 30, "its burn")
    finally:
        for pid in tree_cpu(p.pid):
            os.kill(pid, signal.SIGKILL)
        p.wait()
    assert sorted(role for role, _ in after.values()) == ["other", "router"], after  # the parent has no role
    spent = cpu_between(before, after)
    assert 0.5 <= spent["router"] <= 0.8 and spent["other"] < 0.1, spent
    assert spent["learner"] == spent["actor"] == 0.0
