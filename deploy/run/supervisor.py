"""Child processes with their logs: the one supervisor that ``khgrl up``, the benchmarks and the integration
tests use.

Children are spawned (``subprocess``, never forked from a process with an open Zenoh session) in a new session
of their own (a Ctrl-C at the terminal reaches only the supervisor, which stops them in order), with
``KHGRL_PARENT_PID`` set so that each KhGRL process asks Linux for SIGTERM when its supervisor dies, even by
SIGKILL (:func:`khgrl.common.process.die_with_parent`): no child outlives its launcher.

Each child gets one BLAS/OpenMP thread unless the caller's environment says otherwise (:data:`ONE_THREAD`): every
KhGRL process is one thread of work by design (torch's own threads are set apart: ``--learner-threads``), its
numpy/scipy linear algebra is on matrices of a few hundred rows at most, and a thread pool per process only
oversubscribes the cores the processes share: building the passage world's KMP took 3.9 s with the pools and 1.5 s
without on this 2-core machine while an experiment ran.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from khgrl.common.process import PARENT_ENV

__all__ = ["Proc", "ProcessGroup", "khgrl_argv", "ONE_THREAD"]

ONE_THREAD = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")  # set to 1 in a child, unless given


def khgrl_argv(command: str, *args: str) -> list[str]:
    """argv of ``khgrl COMMAND ARGS`` run by this interpreter (no console script needed)."""
    return [sys.executable, "-m", "khgrl.deploy.cli", command, *args]


class Proc:
    """One child process; stdout and stderr go to ``log_path``."""

    def __init__(self, name: str, argv: list[str], log_path: str | Path, *, env: dict | None = None,
                 cwd: str | Path | None = None, essential: bool = True) -> None:
        self.name = name
        self.argv = list(argv)
        self.log_path = Path(log_path)
        self.essential = essential  # the run fails if it exits non-zero
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "ab")
        env = dict(os.environ if env is None else env)
        env[PARENT_ENV] = str(os.getpid())
        env.setdefault("PYTHONUNBUFFERED", "1")
        for var in ONE_THREAD:
            env.setdefault(var, "1")
        self.popen = subprocess.Popen(self.argv, cwd=cwd, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                      start_new_session=True)
        self.returncode: int | None = None

    @property
    def pid(self) -> int:
        return self.popen.pid

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.popen.poll()
        return self.returncode

    def wait(self, timeout: float) -> int | None:
        """Exit code, or None if still running after ``timeout`` s."""
        try:
            self.returncode = self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        return self.returncode

    def signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def kill(self) -> None:
        """SIGKILL (a crash) and reap."""
        self.signal(signal.SIGKILL)
        self.wait(10)

    def stop(self, timeout: float = 30.0, sig: int | None = None) -> int | None:
        """``sig`` (default SIGTERM; SIGINT: as Ctrl-C), wait up to ``timeout`` s, then SIGKILL."""
        self.signal(signal.SIGTERM if sig is None else sig)
        rc = self.wait(timeout)
        if rc is None:
            self.kill()
        return rc

    def text(self) -> str:
        try:
            self._log.flush()
            return self.log_path.read_text(errors="replace")
        except (OSError, ValueError):
            return ""

    def tail(self, n: int = 30) -> str:
        return "\n".join(self.text().splitlines()[-n:])

    def close(self) -> None:
        if self.poll() is None:
            self.kill()
        self._log.close()


class ProcessGroup:
    """Processes started together; :meth:`stop_all` stops what is left (SIGINT, then SIGKILL), jointly.
    As a context manager it kills whatever is still running on the way out."""

    def __init__(self, log_dir: str | Path, *, env: dict | None = None, cwd: str | Path | None = None) -> None:
        self.log_dir = Path(log_dir)
        self.env = dict(os.environ if env is None else env)
        self.cwd = cwd
        self.procs: list[Proc] = []

    def __enter__(self) -> "ProcessGroup":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self, name: str, argv: list[str], *, essential: bool = True, log_name: str | None = None) -> Proc:
        p = Proc(name, argv, self.log_dir / (log_name or f"{name}.log"), env=self.env, cwd=self.cwd,
                 essential=essential)
        self.procs.append(p)
        return p

    def running(self) -> list[Proc]:
        return [p for p in self.procs if p.poll() is None]

    def wait_all(self, timeout: float, procs: list[Proc] | None = None) -> bool:
        """Wait until ``procs`` (default: all) have exited; False if some still run after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        alive = [p for p in (procs if procs is not None else self.procs) if p.poll() is None]
        while alive and time.monotonic() < deadline:
            time.sleep(0.05)
            alive = [p for p in alive if p.poll() is None]
        return not alive

    def stop_all(self, grace: float = 10.0, kill_after: float = 5.0) -> None:
        """SIGINT to everything still running (a clean stop), SIGKILL to what is left after ``grace`` s."""
        for sig, wait in ((signal.SIGINT, grace), (signal.SIGKILL, kill_after)):
            alive = self.running()
            for p in alive:
                p.signal(sig)
            self.wait_all(wait, alive)

    def close(self) -> None:
        for p in reversed(self.procs):
            p.close()
