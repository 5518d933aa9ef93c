"""The benchmark's processes: KhGRL commands under one :class:`khgrl.deploy.run.supervisor.ProcessGroup`, and waiting
for conditions while watching them."""

from __future__ import annotations

import os
import secrets
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery.transport import free_port, wait_reachable
from khgrl.deploy.run.supervisor import Proc, ProcessGroup, khgrl_argv

__all__ = ["REPO", "TRAIN_FREQ", "BENCH_ACTOR", "BenchProcs", "wait_until", "run_id", "pct", "load",
           "passage_task_file", "task_file"]

REPO = Path(__file__).resolve().parents[2]
TRAIN_FREQ = TQCSettings().train_freq
BENCH_ACTOR = "bench"  # the actor id this process publishes transitions as


class BenchProcs:
    """Routers, learners and actors of one benchmark run, logs in ``WORK/logs/NN-name.log``.

    :param work: the benchmark's work directory
    """

    def __init__(self, work: Path) -> None:
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.setdefault("RUST_LOG", "error")
        self.group = ProcessGroup(work / "logs", env=env, cwd=REPO)

    def start(self, name: str, command: str, *args: str) -> Proc:
        """``khgrl COMMAND ARGS`` as process ``name``."""
        return self.group.start(name, khgrl_argv(command, *args), log_name=f"{len(self.group.procs):02d}-{name}.log")

    def router(self) -> str:
        """A router on a free loopback port; returns its endpoint once it accepts connections."""
        ep = f"tcp/127.0.0.1:{free_port()}"
        p = self.start("router", "router", "--listen", ep)
        try:
            wait_reachable(ep, 30.0, stop=lambda: p.poll() is not None)
        except ConnectionError as exc:
            raise RuntimeError(f"router: {exc}\n{p.tail()}") from None
        return ep

    def learner(self, name: str, run: str, ep: str, run_dir: Path, *extra: str) -> Proc:
        """A learner of run ``run`` (id ``learner``) writing to ``run_dir``, for the passage world's transitions
        (its task descriptor is put where ``khgrl up`` puts it); ``extra``: config flags."""
        passage_task_file(run_dir)
        return self.start(name, "learner", "--run", run, "--connect", ep, "--run-dir", str(run_dir),
                          "--id", "learner", *extra)

    def actor(self, name: str, run: str, ep: str, run_dir: Path, *extra: str) -> Proc:
        """Actor ``a0`` of run ``run`` writing to ``run_dir``; ``extra``: config flags."""
        return self.start(name, "actor", "--run", run, "--connect", ep, "--run-dir", str(run_dir), "--id", "a0",
                          *extra)

    def supervise(self, run: str, ep: str, run_dir: Path) -> Proc:
        """``khgrl supervise``: the heartbeat without which an actor in robot mode holds (the e-stop state kept in
        ``run_dir``)."""
        Path(run_dir).mkdir(parents=True, exist_ok=True)
        return self.start("supervise", "supervise", "--run", run, "--connect", ep, "--state-dir", str(run_dir))

    def close(self) -> None:
        """Stop what still runs (SIGINT, then SIGKILL) and close the logs."""
        self.group.stop_all(grace=10.0, kill_after=5.0)
        self.group.close()


def passage_task_file(run_dir: Path) -> None:
    """``RUN_DIR/learner/task.msgpack`` of the passage world (high_cov), as ``khgrl up`` writes it: a learner
    started by hand takes its spaces from there instead of waiting for an actor to announce the task."""
    task_file(run_dir)


def task_file(run_dir: Path, overrides: dict | None = None) -> None:
    """``RUN_DIR/learner/task.msgpack`` of the run settings ``overrides`` (default: the passage world, high_cov), as
    ``khgrl up`` writes it (kept if it exists).

    :param run_dir: the run directory.
    :param overrides: run settings, e.g. ``{"task": "panda:pick", "adapt": False}``.
    """
    from khgrl.common.config.settings import resolve
    from khgrl.common.delivery.task_link import TASK_FILE, save_task
    from khgrl.deploy.run.preflight import check_task

    path = Path(run_dir) / "learner" / TASK_FILE
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        save_task(path, check_task(resolve(overrides=overrides)))


def wait_until(cond: Callable[[], Any], timeout: float, what: str, procs: tuple[Proc, ...] | list[Proc] = (),
               interval: float = 0.1) -> Any:
    """Poll ``cond()`` until it is truthy (returned); RuntimeError after ``timeout`` s or when one of ``procs``
    exits meanwhile (with its log tail).

    :param cond: the condition (OSError/ValueError/KeyError count as not yet)
    :param timeout: seconds
    :param what: what is waited for (error messages)
    :param procs: processes that must stay alive meanwhile
    :param interval: polling interval in seconds
    """
    deadline = time.monotonic() + timeout
    while True:
        try:
            value = cond()
        except (OSError, ValueError, KeyError):
            value = None
        if value:
            return value
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"{p.name} exited with {p.poll()} while waiting for {what}; log {p.log_path}:\n"
                                   f"{p.tail()}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(interval)


def run_id(tag: str) -> str:
    """A fresh run id (key prefix) for one measurement."""
    return f"bench-{tag}-{secrets.token_hex(3)}"


def pct(values, q: float) -> float | None:
    """The ``q``-th percentile, None for no values."""
    a = np.asarray(values, dtype=float)
    return float(np.percentile(a, q)) if a.size else None


def load() -> list[float]:
    """The machine's load average (1, 5, 15 min)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []
