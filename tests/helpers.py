"""Helpers for integration tests that start real KhGRL processes (router, learner, actors, human input).

Every process is a ``subprocess`` running ``python -c "from MODULE import main; ..."`` in the repository
root (never forked from a process with an open Zenoh session), with its output in a log file. Use
:class:`ProcGroup` as a context manager: whatever is still running at the end is killed by PID.

    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16")
        actor = g.actor(run, ep, "--episodes", "2")
        assert actor.wait(120) == 0, actor.tail()
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

from khgrl.common.delivery.transport import free_port
from khgrl.deploy.run.supervisor import Proc, ProcessGroup

REPO = Path(__file__).resolve().parents[1]

__all__ = ["REPO", "Proc", "ProcGroup", "free_endpoint", "unique_run", "wait_for", "wait_for_file", "read_json",
           "python_main", "TIMING_COLUMNS", "untimed",
           "RecordingPublisher"]


TIMING_COLUMNS = ("wall_time", "human_seconds")  # the episodes.csv columns two runs of one seed differ in


def untimed(rows: list[dict]) -> list[dict]:
    """episodes.csv rows without the columns that measure time (:data:`TIMING_COLUMNS`)."""
    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows]


def unique_run(prefix: str = "t") -> str:
    """A run id (key prefix) no other test uses."""
    return f"{prefix}{os.getpid()}{secrets.token_hex(3)}"


def free_endpoint() -> str:
    """A loopback endpoint on a port the OS gives."""
    return f"tcp/127.0.0.1:{free_port()}"


def python_main(module: str, func: str = "main") -> list[str]:
    """argv prefix that runs ``module.func(argv)`` and exits with its return value."""
    return [sys.executable, "-c", f"from {module} import {func}; import sys; sys.exit({func}(sys.argv[1:]))"]


def wait_for(cond: Callable[[], Any], timeout: float, what: str = "condition", interval: float = 0.1,
             procs: list["Proc"] | None = None) -> Any:
    """Poll ``cond()`` until it returns something truthy (returned) or ``timeout`` s pass (AssertionError).
    If one of ``procs`` exits meanwhile, fail at once with its log tail."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            value = cond()
        except (OSError, ValueError, KeyError):  # a file being written, half-written JSON, ...
            value = None
        if value:
            return value
        for p in procs or []:
            if p.poll() is not None:
                raise AssertionError(f"{p.name} exited with {p.returncode} while waiting for {what}\n{p.tail()}")
        if time.monotonic() > deadline:
            tails = "\n".join(f"--- {p.name}\n{p.tail()}" for p in procs or [])
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}\n{tails}")
        time.sleep(interval)


def wait_for_file(path: str | Path, timeout: float, procs: list["Proc"] | None = None) -> Path:
    path = Path(path)
    wait_for(path.exists, timeout, f"file {path}", procs=procs)
    return path


def read_json(path: str | Path) -> Any:
    return json.loads(Path(path).read_text())


# Networks of 64 x 64 and minibatches of 64 in tests that check what the system does, not how well it learns: the same
# code at a quarter of the learner's CPU time (the tests that check learning, or compare with the paper's sizes,
# give their own --net-arch / --batch-size, or use the defaults through their own command lines).
SMALL_NETS = ["--net-arch", "64", "64"]
# the tests check the system, not how fast it learns: small networks and a quarter of the default update-to-data
# ratio (2 gradient steps per 8 transitions), which leaves the learner's CPU to the processes under test
SMALL_GRADIENT_STEPS = 2
SMALL = [*SMALL_NETS, "--batch-size", "64", "--gradient-steps", str(SMALL_GRADIENT_STEPS)]
# the default ratio (8 per 8), after SMALL, for a test whose timing or scripted behaviour was set on it: a run
# that must last through an attack's phases, a scripted human that acts only where the policy gets to
FULL_UTD = ["--gradient-steps", "8"]
SMALL_UP = "--up-args=" + " ".join(SMALL)  # the same for every run of a khgrl experiment grid


def _unless_given(extra: tuple[str, ...], flags: list[str]) -> list[str]:
    """``flags`` (pairs of --flag values) that ``extra`` does not set itself."""
    out, i = [], 0
    while i < len(flags):
        j = i + 1
        while j < len(flags) and not flags[j].startswith("--"):
            j += 1
        if flags[i] not in extra:
            out += flags[i:j]
        i = j
    return out


class ProcGroup(ProcessGroup):
    """The supervisor of ``khgrl up`` (khgrl.deploy.run.supervisor) with shortcuts for KhGRL processes: starts
    them under
    ``base`` (logs in ``base/logs``) and kills leftovers by PID on exit."""

    def __init__(self, base: str | Path) -> None:
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.setdefault("RUST_LOG", "error")
        super().__init__(Path(base) / "logs", env=env, cwd=REPO)
        self.base = Path(base)

    def start(self, name: str, argv: list[str], **kw) -> Proc:
        return super().start(name, argv, log_name=f"{name}-{len(self.procs)}.log", **kw)

    def router(self, endpoint: str | None = None, timeout: float = 30.0) -> str:
        """Start a router; returns its endpoint once it accepts TCP connections."""
        endpoint = endpoint or free_endpoint()
        p = self.start("router", python_main("khgrl.deploy.run.router") + ["--listen", endpoint])
        host, port = endpoint.split("/", 1)[1].rsplit(":", 1)

        def up() -> bool:
            try:
                with socket.create_connection((host, int(port)), timeout=0.5):
                    return True
            except OSError:
                return False

        wait_for(up, timeout, f"router on {endpoint}", procs=[p])
        return endpoint

    def learner(self, run: str, endpoint: str, *extra: str, run_dir: str | Path | None = None) -> Proc:
        run_dir = Path(run_dir or self.base / "run")
        # the learner stores no more of an actor than its own --max-lead allows (docs/protocol.md, "Flow control");
        # the tests' actors mostly run with --max-lead 100000: so does their learner unless a test says otherwise
        lead = [] if "--max-lead" in extra else ["--max-lead", "100000"]
        return self.start("learner", python_main("khgrl.learner.main") + [
            "--run", run, "--connect", endpoint, "--run-dir", str(run_dir), *lead, *_unless_given(extra, SMALL),
            *extra])

    def actor(self, run: str, endpoint: str, *extra: str, run_dir: str | Path | None = None) -> Proc:
        run_dir = Path(run_dir or self.base / "run")
        return self.start("actor", python_main("khgrl.actor.main") + [
            "--run", run, "--connect", endpoint, "--run-dir", str(run_dir), *_unless_given(extra, SMALL_NETS), *extra])

    def supervise(self, run: str, endpoint: str, run_dir: str | Path | None = None) -> Proc:
        """``khgrl supervise``: the heartbeat without which an actor in robot mode holds (keeping the e-stop state in
        ``run_dir``)."""
        return self.start("supervise", python_main("khgrl.deploy.run.supervise") + [
            "--run", run, "--connect", endpoint, "--state-dir", str(Path(run_dir or self.base / "run"))])

    def human(self, run: str, endpoint: str, *extra: str) -> Proc:
        return self.start("human", python_main("khgrl.human_bridge.main") + [*extra[:1], "--run", run,
                                                                            "--connect", endpoint, *extra[1:]])


# ------------------------------------------------------------------ processes found by their command line
def pids_matching(pattern: str) -> list[int]:
    """PIDs of processes whose full command line matches the regex ``pattern`` (``pgrep -f``), not this one."""
    out = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True, timeout=10)
    return [int(p) for p in out.stdout.split() if int(p) != os.getpid()]


def endpoint_pattern(endpoint: str) -> str:
    """A ``pgrep -f`` regex for the processes started with this endpoint (``--listen``/``--connect``)."""
    host_port = endpoint.split("/", 1)[1]
    return host_port.replace(".", r"\.") + "( |$)"


def pid_alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")


def kill_pids(pids: list[int]) -> None:
    """SIGKILL each PID (by PID, one at a time); already gone is fine."""
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


class RecordingPublisher:
    """Stands in for :class:`khgrl.human_bridge.client.CorrectionPublisher` in tests of a client's answers: records
    what it would send, with the same rule (a live release only after a hold). ``sent`` holds
    ``(actor, p_h as a tuple or None, episode, t, step)``."""

    def __init__(self) -> None:
        self.sent: list[tuple] = []
        self.active: dict[str, bool] = {}

    def send(self, actor, p_h, episode=0, t=0, step=None) -> None:
        if p_h is None and step is None and not self.active.get(actor, False):
            return
        self.sent.append((actor, None if p_h is None else tuple(float(v) for v in p_h), episode, t, step))
        self.active[actor] = p_h is not None


class FakePub:
    """A stand-in for a client's correction publisher: what it would send, in a list."""

    def __init__(self) -> None:
        self.sent: list[tuple] = []

    def send(self, actor, p_h, episode=0, t=0, step=None) -> None:
        import numpy as np

        self.sent.append((actor, None if p_h is None else np.array(p_h), episode, t))


class FakeLink:
    """A stand-in for HumanClient in a pad client's tests: frames from a list, corrections into a list."""

    def __init__(self, client: str = "kb") -> None:
        self.client = client
        self.pub, self.queue, self.flag = FakePub(), [], False
        self.commands: list[str] = []

    def next(self):
        return ("k", self.queue.pop(0)) if self.queue else None

    def publish_status(self) -> None:
        pass

    def control_actors(self, command: str) -> None:
        self.commands.append(command)


def actor_signer(run_dir: str | Path, actor: str):
    """What an actor process ``actor`` of the run in ``run_dir`` signs its batches with: the run's key and its own
    role key (made now if it has none, as ``khgrl keys RUN_DIR --actor ACTOR`` does for a hand-started actor).

    :param run_dir: the run directory.
    :param actor: the actor id.
    """
    from khgrl.common.delivery import run_key
    from khgrl.common.delivery.data_keys import DataKeys
    from khgrl.common.delivery.role_keys import key_id, load_private, make_keys

    kid = key_id("actor", actor)
    make_keys(run_dir, [kid])
    return DataKeys(run=run_key.load(run_dir), kid=kid, private=load_private(run_dir, kid))
