"""The run directory of ``khgrl up``: whether it already holds a run, starting it again (``--overwrite``),
continuing it (``--resume``), and the configuration files written into it.

Layout::

    RUN_DIR/config.toml, config.json  the resolved configuration of the latest start (children read config.json)
    RUN_DIR/config-partN.*            the configuration of part N of a resumed run (part 1: the first start)
    RUN_DIR/summary.json              exit codes, wall time, per-actor results (summary-partN.json: earlier parts)
    RUN_DIR/pids.json                 the launcher's and its children's process ids (latest start)
    RUN_DIR/logs/<process>.log        each process's output (appended to by a resumed run)
    RUN_DIR/learner/...               checkpoints, TensorBoard scalars
    RUN_DIR/actor-<id>/...            episodes.csv/json, summary.json, corrections.csv, tb/, steps/
    RUN_DIR/demos.npz (or .csv)       the demonstrations of ``--demos`` (a ``lerobot:`` source resampled)

A resumed run is one run in several parts: ``config.json`` always describes the part now running (its
``runtime`` says ``resumed``, ``part`` and ``first_started``); the earlier parts' ``config.json``,
``config.toml`` and ``summary.json`` are kept as ``*-partN.*``.
"""

from __future__ import annotations

import fcntl
import json
import os
import secrets
import shutil
from pathlib import Path

__all__ = ["RunDirError", "results_in", "has_checkpoint", "clear_run", "live_run", "still_running", "refuse_live",
           "archive_part", "previous_runtime", "make_run_id", "write_pids", "resolve_demos", "keep_demos"]

# entries that mark a directory as holding (part of) a run; --overwrite deletes exactly these
_RESULT_FILES = ("config.json", "config.toml", "summary.json", "pids.json", "estop.json")  # (--resume keeps estop.json)
_RESULT_DIRS = ("learner", "logs", "certs")
_RESULT_GLOBS = ("actor-*", "config-part*", "summary-part*", "human-*")


class RunDirError(Exception):
    """A run directory that cannot be used as asked (``khgrl up`` exits 2 with this message)."""


def results_in(run_dir: Path) -> list[str]:
    """Names of the entries of ``run_dir`` that belong to an earlier run (empty: the directory is free).

    :param run_dir: the run directory (need not exist)
    """
    if not run_dir.is_dir():
        return []
    found = [n for n in (*_RESULT_FILES, *_RESULT_DIRS) if (run_dir / n).exists()]
    for pattern in _RESULT_GLOBS:
        found += sorted(p.name for p in run_dir.glob(pattern))
    return found


def has_checkpoint(run_dir: Path, checkpoint_dir: str | Path = "") -> bool:
    """Whether the learner left something to resume from: a complete checkpoint (``state.json`` in
    ``learner/checkpoint`` or in the previous one, ``learner/checkpoint.old``) or its journal
    (``learner/journal/segment-*.bin``, see :func:`khgrl.learner.checkpoint.can_resume`).

    :param run_dir: the run directory
    :param checkpoint_dir: the learner's ``--checkpoint-dir`` (empty: ``RUN_DIR/learner``)
    """
    base = Path(checkpoint_dir) if checkpoint_dir else run_dir / "learner"
    return any((base / d / "state.json").is_file() for d in ("checkpoint", "checkpoint.old")) or \
        any((base / "journal").glob("segment-*.bin"))


def clear_run(run_dir: Path) -> list[str]:
    """Delete an earlier run's entries (only those :func:`results_in` names; other files stay).

    :param run_dir: the run directory
    :returns: the names deleted
    """
    names = results_in(run_dir)
    for name in names:
        path = run_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    return names


def live_run(run_dir: Path) -> list[str]:
    """What of the run in ``run_dir`` is still alive (empty: nothing): its launcher and children of ``pids.json``
    that still run KhGRL, and actors holding their ``actor-ID/actor.lock`` (processes started by hand too).

    :param run_dir: the run directory
    """
    try:
        pids = json.loads((run_dir / "pids.json").read_text())
    except (OSError, ValueError):
        pids = {}
    pids = pids if isinstance(pids, dict) else {}
    children = pids.get("children") if isinstance(pids.get("children"), dict) else {}
    alive = [f"{name} (pid {pid})" for name, pid in [("launcher", pids.get("launcher")), *children.items()]
             if isinstance(pid, int) and pid != os.getpid() and _runs_khgrl(pid)]
    return alive + [f"{lock.parent.name} (it holds {lock.parent.name}/{lock.name})"
                    for lock in sorted(run_dir.glob("actor-*/actor.lock")) if _locked(lock)]


def still_running(run_dir: Path, command: str) -> str:
    """Why ``command`` should not read ``run_dir`` now ("" when its run has ended): it reads a finished run, and a
    live one's files are half written (``khgrl export`` and ``khgrl view`` took what was there, silently).

    :param run_dir: the run directory
    :param command: the command that asks (``khgrl export``, ``khgrl view``, ``khgrl eval``)
    """
    alive = live_run(run_dir)
    return (f"the run in {run_dir} is still running ({', '.join(alive)}): {command} reads a finished run -- wait for "
            f"it to end, or stop it (khgrl stop {run_dir})") if alive else ""


def refuse_live(run_dir: Path) -> None:
    """``--overwrite``: refuse a run directory whose run is still alive (:func:`live_run`).

    :param run_dir: the run directory
    :raises RunDirError: naming what is alive
    """
    if alive := live_run(run_dir):
        raise RunDirError(f"--overwrite: the run in {run_dir} is still running ({', '.join(alive)}): stop it first "
                          f"(khgrl stop {run_dir}), or give another --run-dir")


def _runs_khgrl(pid: int) -> bool:
    """Whether process ``pid`` is alive (not a zombie) and, where ``/proc`` says, runs KhGRL (a pid reused since
    by another program is not the run's)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's process: alive
    proc = Path(f"/proc/{pid}")
    try:
        if (proc / "stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
            return False
        return b"khgrl" in (proc / "cmdline").read_bytes()
    except (OSError, IndexError):
        return True  # (no /proc here: alive as far as the signal says)


def _locked(path: Path) -> bool:
    """Whether a process holds the ``flock`` on ``path`` (:mod:`khgrl.common.delivery.restart`)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)  # (closing releases a lock taken here)
    return False


def previous_runtime(run_dir: Path) -> dict:
    """The ``runtime`` table of the run directory's ``config.json`` ({} if there is none or it is unreadable).

    :param run_dir: the run directory
    """
    try:
        data = json.loads((run_dir / "config.json").read_text())
    except (OSError, ValueError):
        return {}
    runtime = data.get("runtime") if isinstance(data, dict) else None
    return runtime if isinstance(runtime, dict) else {}


def archive_part(run_dir: Path, part: int) -> None:
    """Keep the configuration and summary of part ``part`` of a resumed run as ``*-partN.*`` before the next
    part writes its own.

    :param run_dir: the run directory
    :param part: the number of the part that ran before (1: the first start)
    """
    for name in ("config.json", "config.toml", "summary.json"):
        src = run_dir / name
        if src.is_file():
            stem, _, suffix = name.partition(".")
            src.replace(run_dir / f"{stem}-part{part}.{suffix}")


def make_run_id(run_dir: Path) -> str:
    """A run id (key prefix) from the directory's name and a random suffix, e.g. ``demo-3fa2c1``.

    :param run_dir: the run directory
    """
    stem = "".join(c if c.isalnum() or c in "-_" else "-" for c in run_dir.name)[:40] or "run"
    return f"{stem}-{secrets.token_hex(3)}"


def write_pids(run_dir: Path, launcher: int, children: dict[str, int]) -> None:
    """``RUN_DIR/pids.json``: who to look for (and stop) if a launcher dies.

    :param run_dir: the run directory
    :param launcher: the launcher's process id
    :param children: process id by process name
    """
    (run_dir / "pids.json").write_text(json.dumps({"launcher": launcher, "children": children}, indent=2))


def resolve_demos(demos: str) -> str:
    """A ``--demos`` value with its path made absolute (children run elsewhere): a file, or the folder of a
    ``lerobot:PATH?...`` source.

    :param demos: the ``--demos`` value.
    """
    from khgrl.common.lerobot.demos import is_lerobot_spec, parse_spec

    return parse_spec(demos, resolve=True).text() if is_lerobot_spec(demos) else str(Path(demos).resolve())


def keep_demos(run_dir: Path, task_spec: str, demos: str) -> Path:
    """Keep the demonstrations a run is trained from in the run directory; returns the kept file, which the
    processes then read: a file is copied (``RUN_DIR/demos.npz`` or ``.csv``); a ``lerobot:`` source is written
    resampled as ``RUN_DIR/demos.npz`` (array ``demos``, (M, N, O), and ``source``, the spec it came from).

    :param run_dir: the run directory.
    :param task_spec: the run's task (a ``lerobot:`` source is resampled to its N).
    :param demos: the resolved ``--demos`` value.
    """
    import numpy as np
    from khgrl.common.lerobot.demos import is_lerobot_spec
    from khgrl.common.tasks.api import load_task

    run_dir.mkdir(parents=True, exist_ok=True)
    if not is_lerobot_spec(demos):
        kept = run_dir / f"demos{Path(demos).suffix}"
        shutil.copyfile(demos, kept)
        return kept.resolve()
    kept = run_dir / "demos.npz"
    np.savez_compressed(kept, demos=load_task(task_spec, demos).demos, source=np.array(demos))
    return kept.resolve()
