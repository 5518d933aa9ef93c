"""The worker's side of ``khgrl experiment --ray`` (:mod:`khgrl.deploy.experiments.experiment_ray`): the Ray
task that runs
one ``khgrl up`` in a scratch directory and sends the finished run folder back, and the check that the worker's
khgrl is the head's."""

from __future__ import annotations

import ctypes
import io
import os
import platform
import re
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import khgrl

__all__ = ["EPISODE_LINE", "khgrl_identity", "check_identity", "pack_run", "run_on_worker", "run_env"]

EPISODE_LINE = re.compile(r"\[a0\] episode (\d+):|^\s*(\d+)/(\d+) episodes")  # a run's progress in its output
LOG_TAIL_LINES = 40
_SCRATCH = "khgrl-ray"  # under the worker's temporary directory
_PR_SET_PDEATHSIG = 1


def khgrl_identity() -> dict[str, str]:
    """This khgrl's version and, for a git checkout, its commit (``""`` otherwise)."""
    root = Path(khgrl.__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10).stdout.strip() if (root / ".git").exists() else ""
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return {"version": khgrl.__version__, "commit": commit}


def check_identity(head: dict[str, str]) -> None:
    """Raise when this (worker's) khgrl is not the head's: another version, or another commit of a checkout.

    :param head: :func:`khgrl_identity` on the head
    """
    mine = khgrl_identity()
    same_commit = not (head.get("commit") and mine["commit"]) or head["commit"] == mine["commit"]
    if head.get("version") != mine["version"] or not same_commit:
        raise RuntimeError(f"khgrl on {platform.node()} is {mine}, the head's is {head}: install the head's khgrl "
                           "on every Ray worker")


def pack_run(run_dir: Path) -> bytes:
    """The run folder as tar.gz bytes (paths relative to it).

    :param run_dir: a finished run's directory
    """
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=6) as tar:
        for child in sorted(run_dir.iterdir()):
            tar.add(child, arcname=child.name)
    return buf.getvalue()


def _child_setup() -> None:
    """In the run's ``khgrl up``, before exec: SIGINT and SIGTERM as in a shell (a Ray worker ignores or blocks
    some, which its children would inherit: the router then ignores the launcher's stop and is killed), and
    SIGTERM (a clean stop) when the Ray worker dies, even by SIGKILL."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_SETMASK, [])
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def _sweep_scratch(base: Path) -> None:
    """Remove scratch directories of dead workers (a force-cancelled task cannot remove its own)."""
    for d in base.glob("*-*"):
        try:
            os.kill(int(d.name.split("-")[0]), 0)
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
        except (ValueError, PermissionError):
            continue


def _stop(proc: subprocess.Popen) -> None:
    """Stop a run's ``khgrl up`` that is still running: SIGINT to its group (a clean stop), then SIGKILL."""
    for sig, wait in ((signal.SIGINT, 30.0), (signal.SIGKILL, 10.0)):
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, sig)
            proc.wait(wait)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            continue


def run_on_worker(name: str, argv: list[str], head_run_dir: str, head: dict[str, str], head_paths: list[str]
                  ) -> Iterator[dict]:
    """The Ray task (a streaming generator): run one ``khgrl up`` in a scratch directory on this worker.

    Yields ``{"event": "start", "node"}``, ``{"event": "episode", "episode"}`` per finished episode, and last
    ``{"event": "end", "node", "returncode", "wall_time_s", "tar", "log_tail"}``.

    :param name: the run's name (its directory's)
    :param argv: the run's command on the head (its Python and run directory are replaced by this worker's)
    :param head_run_dir: the run directory in ``argv``
    :param head: the head's :func:`khgrl_identity`
    :param head_paths: directories the head imports tasks from (its working directory): those that exist on this
        worker (the same host, a shared file system) go first on the run's ``PYTHONPATH``, so a task module that
        ``khgrl experiment`` without ``--ray`` imports is imported here too
    """
    check_identity(head)
    node = platform.node()
    yield {"event": "start", "node": node}
    base = Path(tempfile.gettempdir()) / _SCRATCH
    base.mkdir(exist_ok=True)
    _sweep_scratch(base)
    scratch = Path(tempfile.mkdtemp(prefix=f"{os.getpid()}-", dir=base))
    try:
        run_dir = scratch / name
        run_dir.mkdir()
        cmd = [sys.executable, *(str(run_dir) if a == head_run_dir else a for a in argv[1:])]
        t0 = time.time()
        with open(run_dir / "experiment.log", "w") as log:
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                                    env=run_env(head_paths), start_new_session=True,
                                    preexec_fn=_child_setup, cwd=scratch)
            try:
                for line in proc.stdout:
                    log.write(line)
                    log.flush()
                    m = EPISODE_LINE.search(line)
                    if m:
                        yield {"event": "episode", "episode": int(m.group(1) or m.group(2))}
                rc = proc.wait()
            finally:
                _stop(proc)  # cancelled (KeyboardInterrupt) or failed mid-run: no khgrl up left behind
        wall = time.time() - t0
        tail = (run_dir / "experiment.log").read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:]
        yield {"event": "end", "node": node, "returncode": rc, "wall_time_s": round(wall, 1), "tar": pack_run(run_dir),
               "log_tail": "\n".join(tail)}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)




def run_env(head_paths: list[str]) -> dict[str, str]:
    """The environment of a run's ``khgrl up`` on this worker: this worker's, with the head's task directories
    that exist here first on ``PYTHONPATH``.

    :param head_paths: see :func:`run_on_worker`
    """
    here = [p for p in head_paths if os.path.isdir(p)]
    path = os.pathsep.join([*here, *filter(None, [os.environ.get("PYTHONPATH", "")])])
    return {**os.environ, "PYTHONUNBUFFERED": "1", **({"PYTHONPATH": path} if path else {})}
