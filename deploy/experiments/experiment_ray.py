"""``khgrl experiment --ray ADDRESS``: the experiment's runs as Ray tasks on a cluster's workers.

Design. The head (the ``khgrl experiment`` process, a Ray driver) plans the grid exactly as without Ray and skips
every run whose directory ``OUT/<name>`` holds a finished result. Each other run becomes one Ray task
(:func:`run_on_worker`, ``.options(num_cpus=--ray-cpus, num_gpus=--ray-gpus, max_retries=2)``: Ray re-runs it if its
worker dies) that runs on some worker node:

1. it checks that the worker's khgrl is the head's (version, and git commit where both are checkouts) and fails
   clearly otherwise -- the workers must have khgrl installed, the same version, in the Python that runs Ray;
2. it starts the run's ``khgrl up`` (the argv the local path builds: its own router on a free port and its own
   processes) in a scratch directory under the worker's temporary directory, with ``PR_SET_PDEATHSIG`` so that a
   killed task takes its ``khgrl up`` with it, and streams ``start`` (the node) and ``episode`` events back;
3. it returns the whole finished run folder as one tar.gz (everything, ``learner/checkpoint/replay_buffer.pkl``
   included: the buffer is preallocated and compresses to little, a 2-episode run packs to ~5 MB, most of it the
   two copies of ``model.zip``; keeping it all makes a Ray run's folder the same as a local one) with the exit
   code, wall time and the log's tail, and removes its scratch directory.

The head unpacks a finished run into a temporary directory beside ``OUT/<name>`` and renames it into place only
if it holds a finished run (:func:`unpack_run`), so ``OUT`` never holds half a run: a failed task (nonzero exit,
a worker that died more often than the retries, a version mismatch) is recorded in ``OUT/experiment.json`` as
failed with its log tail and leaves no folder; running the command again redoes it. Ctrl-C cancels the tasks
(first ``ray.cancel``, which lets a task stop its run, then ``ray.cancel(force=True)``) and writes nothing more.
The files of a Ray run name the worker's scratch directory as their run directory (where it ran), and
``experiment.json`` records the node of each run.

Ray is imported only here and only when ``--ray`` is given (``pip install 'khgrl[ray]'``).
"""

from __future__ import annotations

import argparse
import gzip
import io
import os
import secrets
import shutil
import sys
import tarfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from khgrl.deploy.experiments.experiment_progress import last_line
from khgrl.deploy.experiments.ray_worker import EPISODE_LINE, khgrl_identity, run_on_worker

__all__ = ["EPISODE_LINE", "DEFAULT_CPUS", "check_ray_settings", "add_ray_arguments", "import_ray", "unpack_run",
           "RayRunner"]

DEFAULT_CPUS = 2.0  # a run's learner and actor, one core each
MAX_RETRIES = 2  # Ray re-runs a task whose worker died, this many times
CANCEL_GRACE_S = 15.0  # after ray.cancel, before ray.cancel(force=True)
WAIT_HINT_S = 120.0  # no run started this long after submitting: say what they need


def check_ray_settings(address: str, cpus: float, gpus: float, system: str) -> None:
    """Refuse a bad ``ray``/``ray_cpus``/``ray_gpus`` of an experiment configuration.

    :param address: ``""`` (no Ray), a Ray address, ``auto`` or ``local``
    :param cpus: CPUs Ray reserves per run (> 0)
    :param gpus: GPUs Ray reserves per run (>= 0; > 0 asks the learner for ``--device cuda``)
    :param system: the experiment's system (GPUs only for ``distributed``)
    """
    if not isinstance(address, str):
        raise ValueError(f"ray must be an address string ('auto', 'local', 'HOST:PORT'), not {address!r}")
    for key, value in (("ray_cpus", cpus), ("ray_gpus", gpus)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
            raise ValueError(f"{key} must be a number, not {value!r}")
    if cpus <= 0 or gpus < 0:
        raise ValueError(f"ray_cpus must be > 0 and ray_gpus >= 0, got {cpus} and {gpus}")
    if gpus > 0 and system != "distributed":
        raise ValueError("ray_gpus is for the distributed system's learner (khgrl up --device cuda)")


def add_ray_arguments(p: argparse.ArgumentParser) -> None:
    """``--ray``, ``--ray-cpus`` and ``--ray-gpus`` of ``khgrl experiment``.

    :param p: the experiment's parser
    """
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="run each unfinished run as a Ray task on a cluster: HOST:PORT, ray://HOST:PORT, auto (the "
                        "cluster of this node), or local (start Ray in this process); the workers need khgrl, the "
                        "same version (pip install 'khgrl[ray]'); --jobs is then ignored (default: no Ray, local runs)")
    p.add_argument("--ray-cpus", type=float, default=None,
                   help=f"CPUs Ray reserves per run (default {DEFAULT_CPUS:g}: learner + actor)")
    p.add_argument("--ray-gpus", type=float, default=None,
                   help="GPUs Ray reserves per run; > 0 runs the learner with --device cuda (default 0)")


def import_ray() -> Any:
    """The ``ray`` module, or a clear error when it is not installed."""
    try:
        import ray
    except ImportError as exc:
        raise RuntimeError("khgrl experiment --ray needs Ray: pip install 'khgrl[ray]'") from exc
    return ray


def unpack_run(data: bytes, dest: Path, accept: Callable[[Path], bool] | None = None) -> bool:
    """Unpack :func:`pack_run`'s bytes into ``dest`` atomically: into a temporary directory beside it, then one
    rename. ``dest`` must not exist (nothing is overwritten); nothing is left behind when the archive is bad or
    ``accept`` refuses the unpacked folder.

    :param data: tar.gz bytes
    :param dest: the run directory to create
    :param accept: checks the unpacked folder (e.g. that it holds a finished run)
    :return: whether ``dest`` now holds the run
    :raises ValueError: for a broken archive or one with paths outside the run
    """
    if dest.exists():
        raise FileExistsError(f"{dest} exists: not overwritten")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.parent / f".{dest.name}.{os.getpid()}.{secrets.token_hex(4)}.unpacking"
    tmp.mkdir()  # as the local path's run directories: the umask's mode
    try:
        try:
            with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
                tar.extractall(tmp, filter="data")  # no absolute paths, no escapes from tmp, no devices
        except (tarfile.TarError, EOFError, zlib.error, gzip.BadGzipFile) as exc:
            raise ValueError(f"{dest.name}: a broken or unsafe run archive: {exc}") from exc
        if accept is not None and not accept(tmp):
            return False
        if dest.exists():
            raise FileExistsError(f"{dest} appeared while unpacking: not overwritten")
        os.rename(tmp, dest)
        return True
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # gone after the rename; else the half or refused unpacking


class Runner(Protocol):
    """What :class:`RayRunner` uses of the experiment's local runner
    (``khgrl.deploy.experiments.experiment._Runner``)."""

    cfg: Any
    out: Path
    progress: Any
    stopping: bool

    def record(self, name: str, **info) -> None: ...


class RayRunner:
    """The head's side: submit the unfinished runs as Ray tasks, follow them, unpack and record what comes back.

    :param runner: the experiment's runner (configuration, output directory, progress, ``record``, ``stopping``)
    :param argv_of: a run's command (``run_argv``), from its spec
    :param is_done: whether a directory holds a finished run (``run_is_done``)
    """

    def __init__(self, runner: Runner, argv_of: Callable[[Any], list[str]], is_done: Callable[[Path], bool]) -> None:
        self.runner, self.argv_of, self.is_done = runner, argv_of, is_done
        self.cfg = runner.cfg
        self.live: dict[str, Any] = {}  # run name -> its task's ObjectRefGenerator
        self.status: dict[str, str] = {}
        self.started = False  # a task has started on a worker

    def _init(self, ray: Any) -> None:
        address = self.cfg.ray
        try:
            if address == "local":  # a Ray of this process only, for users without a cluster
                os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
                ray.init(address="local", include_dashboard=False, log_to_driver=False, logging_level="WARNING")
            else:
                ray.init(address=address, log_to_driver=False, logging_level="WARNING")
        except (ConnectionError, ValueError) as exc:
            raise RuntimeError(f"no Ray cluster at {address!r}: {exc}") from exc

    def _submit(self, ray: Any, specs: list) -> None:
        task = ray.remote(run_on_worker)
        head = khgrl_identity()
        for spec in specs:
            run_dir = self.runner.out / spec.name
            if self.is_done(run_dir):
                self.runner.progress.skip(spec.name)
                self.runner.record(spec.name, status="done", reused=True)
                self.status[spec.name] = "done"
                continue
            if run_dir.exists():
                shutil.rmtree(run_dir)  # interrupted or failed before: start again from scratch
            argv = self.argv_of(spec) + (["--device", "cuda"] if self.cfg.ray_gpus > 0 else [])
            self.live[spec.name] = task.options(num_cpus=self.cfg.ray_cpus, num_gpus=self.cfg.ray_gpus,
                                                max_retries=MAX_RETRIES, name=spec.name).remote(
                spec.name, argv, str(run_dir), head, [os.getcwd()])
            self.runner.record(spec.name, status="queued", argv=argv, ray=self.cfg.ray)

    def _event(self, name: str, item: dict) -> None:
        progress = self.runner.progress
        if item["event"] == "start":
            self.started = True
            progress.start(name, note=f"running on {item['node']}")
            self.runner.record(name, status="running", node=item["node"], started=time.strftime("%Y-%m-%dT%H:%M:%S"))
        elif item["event"] == "episode":
            progress.advance(name, item["episode"])
        elif item["event"] == "end":
            self.live.pop(name)
            try:  # finished, even during a Ctrl-C: kept
                error = ""
                ok = item["returncode"] == 0 and unpack_run(item["tar"], self.runner.out / name, self.is_done)
            except (ValueError, OSError) as exc:  # a broken archive, OUT/<name> made meanwhile, a full disk
                ok, error = False, str(exc)
            status = "done" if ok else ("interrupted" if self.runner.stopping else "failed")
            extra = {} if ok else {"log_tail": item["log_tail"], **({"error": error} if error else {})}
            self._finish(name, status, item["wall_time_s"], returncode=item["returncode"], node=item["node"], **extra)

    def _finish(self, name: str, status: str, wall: float, **info) -> None:
        self.status[name] = status
        self.runner.record(name, status=status, wall_time_s=wall, **info)
        why = info.get("error") or last_line(info.get("log_tail", ""))
        self.runner.progress.finish(name, status, wall, why)

    def _failed(self, name: str, exc: BaseException) -> None:
        """A task that raised (version mismatch, worker died past the retries) or was cancelled."""
        self.live.pop(name, None)
        text = str(exc).strip() or type(exc).__name__
        line = text.splitlines()[-1][:500]
        if "No module named 'khgrl" in text:
            line = f"khgrl is not installed on the worker (install the head's khgrl there): {line}"
        status = "interrupted" if self.runner.stopping else "failed"
        self._finish(name, status, 0.0, error=line, log_tail=text[-4000:])

    def _cancel(self, ray: Any) -> None:
        """Ctrl-C: cancel every task (a KeyboardInterrupt in it stops its run), then kill what is left."""
        for gen in self.live.values():
            ray.cancel(gen)
        deadline = time.time() + CANCEL_GRACE_S
        while self.live and time.time() < deadline:
            self._poll(ray)
        for gen in self.live.values():
            ray.cancel(gen, force=True)

    def _poll(self, ray: Any) -> None:
        names = {id(g): n for n, g in self.live.items()}
        ready, _ = ray.wait(list(self.live.values()), num_returns=len(self.live), timeout=0.5)
        for gen in ready:
            name = names[id(gen)]
            try:
                item = ray.get(next(gen))
            except StopIteration:
                self._failed(name, RuntimeError("the task ended without a result"))
                continue
            except Exception as exc:  # RayTaskError, WorkerCrashedError, TaskCancelledError, ...
                self._failed(name, exc)
                continue
            self._event(name, item)

    def run_all(self, specs: list) -> list[str]:
        """Run ``specs`` on the cluster; return each one's status (``done``, ``failed``, ``interrupted``).

        :param specs: the planned runs (``RunSpec``)
        """
        ray = import_ray()
        self._init(ray)
        try:
            self._submit(ray, specs)
            cancelled, hint_at = False, time.time() + WAIT_HINT_S
            while self.live:
                if not self.started and time.time() > hint_at:
                    hint_at = float("inf")
                    print(f"khgrl experiment: no run started on {self.cfg.ray} after {WAIT_HINT_S:.0f} s: does a "
                          f"node have {self.cfg.ray_cpus:g} CPUs and {self.cfg.ray_gpus:g} GPUs free? (ray status)",
                          file=sys.stderr, flush=True)
                if self.runner.stopping and not cancelled:
                    cancelled = True
                    self._cancel(ray)
                    for name in list(self.live):  # force-cancelled: nothing more will come
                        self._failed(name, RuntimeError("cancelled"))
                    break
                self._poll(ray)
        finally:
            ray.shutdown()
        return [self.status.get(s.name, "not started") for s in specs]
