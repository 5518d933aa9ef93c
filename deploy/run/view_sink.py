"""``khgrl up --view``: the run in Rerun, live or into a file.

* ``--view none`` (default): nothing (no Rerun import anywhere);
* ``--view rerun``: spawns Rerun's native viewer (it stays open after the run) and every process logs to it;
* ``--view rerun:FILE.rrd``: no viewer; the launcher starts Rerun's own CLI as a single sink, ``rerun --port P
  --save FILE`` on a free loopback port, and every process streams to it over gRPC: one file, one recording,
  whichever processes log. An existing FILE is refused unless ``--overwrite``. The sink writes what arrives as it
  arrives, so a killed actor leaves what it had sent; it is stopped (SIGTERM) after the run's processes exited;
* ``--view rerun:web``: the same sink with Rerun's web viewer (``rerun --serve-web``); its URL is printed; it is
  stopped with the run like the file sink (nothing is left behind; ``khgrl view RUN_DIR`` shows the run later).

The launcher tells its children where to log in ``$KHGRL_VIEW`` (:class:`~khgrl.common.rerun_log.ViewTarget`;
actors: :mod:`khgrl.actor.viewer`) and logs the learner's numbers itself, from the statuses it receives anyway
(``/learner/utd``, ``ingested``, ``version``, ``grad_steps_per_s`` on the ``ingested`` timeline): the learner
process, which trains at nice 5, loads no Rerun and sends nothing more.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

from khgrl.common.delivery.transport import free_port
from khgrl.common.rerun_log import VIEW_ENV, RunLogger, ViewTarget, has_display, import_rerun, open_recording

__all__ = ["ViewSpec", "RunView", "add_view_flags", "parse_view", "run_view", "rerun_binary"]

SINK_START_S = 15.0  # the sink must listen within this
SINK_STOP_S = 10.0  # after SIGTERM


@dataclass(frozen=True)
class ViewSpec:
    """A parsed ``--view``: ``kind`` none, spawn, file or web; ``file`` for kind file."""

    kind: str = "none"
    file: Path | None = None


def add_view_flags(parser: argparse.ArgumentParser) -> None:
    """``--view`` and ``--view-camera-every`` (``khgrl up``)."""
    parser.add_argument("--view", default="none", metavar="SPEC",
                        help="watch the run in Rerun (pip install 'khgrl[view]'): none; rerun (spawn the native "
                             "viewer); rerun:FILE.rrd (record into FILE, no viewer; an existing FILE needs "
                             "--overwrite); rerun:web (serve the web viewer, print its URL) (default: %(default)s)")
    parser.add_argument("--view-camera-every", type=int, default=10, metavar="K",
                        help="with --view: the actor logs the simulator's camera image every K steps where the task "
                             "has one (Fetch, Panda; about 10 ms a 256 x 256 image on a CPU); 0: never "
                             "(default: %(default)s)")


def parse_view(spec: str, overwrite: bool = False, run_dir: Path | None = None) -> ViewSpec:
    """Check ``--view SPEC`` (before anything is written); ValueError naming the problem.

    :param spec: none, rerun, rerun:web or rerun:FILE.rrd.
    :param overwrite: an existing FILE may be replaced.
    :param run_dir: the run directory (a FILE in it may be in folders not made yet).
    """
    if spec in ("", "none"):
        return ViewSpec()
    if spec not in ("rerun", "rerun:web") and not spec.startswith("rerun:"):
        raise ValueError(f"--view {spec!r}: expected none, rerun, rerun:FILE.rrd or rerun:web")
    try:
        import_rerun()
    except ImportError as exc:
        raise ValueError(f"--view {spec}: {exc}") from None
    if spec == "rerun":
        if not has_display():
            raise ValueError("--view rerun spawns Rerun's native viewer, which needs a display: record with "
                             "--view rerun:FILE.rrd or serve the web viewer with --view rerun:web")
        return ViewSpec("spawn")
    if spec == "rerun:web":
        return ViewSpec("web")
    path = Path(spec[len("rerun:"):])
    if path.suffix != ".rrd":
        raise ValueError(f"--view {spec!r}: the recording file must end in .rrd")
    if path.exists() and not overwrite:
        raise ValueError(f"--view: {path} exists: give --overwrite to replace it, or another file")
    inside = run_dir is not None and path.resolve().is_relative_to(Path(run_dir).resolve())
    if not path.resolve().parent.is_dir() and not inside:
        raise ValueError(f"--view: no directory {path.resolve().parent} for {path.name}")
    return ViewSpec("file", path.resolve())


def run_view(args: argparse.Namespace, plan: Any) -> "RunView":
    """``khgrl up``'s view from its flags (ValueError for a bad ``--view``; the sink's log in RUN_DIR/logs).

    :param args: ``--view``, ``--view-camera-every``, ``--overwrite``.
    :param plan: the run's :class:`~khgrl.deploy.run.plan.RunPlan` (run id, directory, actors).
    """
    return RunView(parse_view(args.view, args.overwrite, plan.run_dir), plan.run_id, args.view_camera_every,
                   Path(plan.run_dir) / "logs", tuple(plan.cfg.actor_ids()))


def rerun_binary() -> str:
    """The ``rerun`` executable shipped with rerun-sdk (the binary itself: a signal reaches it, not a wrapper)."""
    import rerun_cli

    return str(Path(rerun_cli.__file__).parent / "rerun")


def _die_with_launcher() -> None:
    """(In the sink, before exec) SIGTERM when the launcher dies, even by SIGKILL (Linux)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG


def _wait_listening(port: int, proc: subprocess.Popen | None, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise ConnectionError(f"the Rerun sink exited at start (code {proc.returncode})")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise ConnectionError(f"the Rerun sink did not listen on port {port} within {timeout:g} s")


class RunView:
    """The run's view (``--view``), a context manager around the run: starts the sink or viewer, gives the children
    their :data:`~khgrl.common.rerun_log.VIEW_ENV`, logs the learner's statuses, stops the sink at the end.

    :param spec: the parsed ``--view``.
    :param run_id: the run id (the recording id).
    :param camera_every: ``--view-camera-every``.
    :param log_dir: where the sink's log goes (``RUN_DIR/logs``).
    :param actors: the run's actor ids.
    """

    def __init__(self, spec: ViewSpec = ViewSpec(), run_id: str = "", camera_every: int = 10,
                 log_dir: Path | None = None, actors: tuple[str, ...] = ()) -> None:
        if camera_every < 0:
            raise ValueError("--view-camera-every must be >= 0")
        self.spec, self.run_id, self.camera_every, self.log_dir = spec, run_id, camera_every, log_dir
        self.actors = tuple(actors)
        self.sink: subprocess.Popen | None = None
        self.url = ""
        self.logger: RunLogger | None = None
        self._failed = False
        self._out: Any = None

    def __enter__(self) -> "RunView":
        if self.spec.kind == "none":
            return self
        try:
            self._start()
        except (OSError, ConnectionError) as exc:  # the run goes on without its view
            print(f"khgrl up: error: no Rerun view: {exc}", file=sys.stderr, flush=True)
            self.spec, self.logger = ViewSpec(), None
        return self

    def _start(self) -> None:
        port = free_port()
        self.url = f"rerun+http://127.0.0.1:{port}/proxy"
        if self.spec.kind == "spawn":
            import_rerun().spawn(port=port, connect=False, hide_welcome_screen=True)
            _wait_listening(port, None, SINK_START_S)
        else:
            self.sink = self._start_sink(port)
        self.logger = RunLogger(open_recording(self.run_id, url=self.url), "launcher")

    def _start_sink(self, port: int) -> subprocess.Popen:
        argv = [rerun_binary(), "--bind", "127.0.0.1", "--port", str(port)]
        if self.spec.kind == "file":
            self.spec.file.unlink(missing_ok=True)  # (--overwrite: checked before)
            self.spec.file.parent.mkdir(parents=True, exist_ok=True)  # (in the run directory)
            argv += ["--save", str(self.spec.file)]
        else:
            web = free_port()
            argv += ["--serve-web", "--web-viewer-port", str(web)]
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            self._out = open(self.log_dir / "rerun.log", "ab")
        # the sink ends with the launcher (it is stopped at the end, and dies with it; a new session: a Ctrl-C
        # goes to the launcher first): nothing is left behind
        proc = subprocess.Popen(argv, stdout=self._out or subprocess.DEVNULL, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True, preexec_fn=_die_with_launcher)
        _wait_listening(port, proc, SINK_START_S)
        if self.spec.kind == "web":
            print(f"khgrl up: Rerun web viewer at http://127.0.0.1:{web}/?url={quote(self.url, safe='')} (until "
                  f"the run ends; afterwards: khgrl view RUN_DIR)", flush=True)
        return proc

    def env(self) -> dict[str, str]:
        """The environment of the run's children (``$KHGRL_VIEW`` when viewed; offscreen MuJoCo for the camera)."""
        env = dict(os.environ)
        if self.spec.kind != "none":
            env[VIEW_ENV] = ViewTarget(self.url, self.camera_every, actors=self.actors).to_env()
            if not env.get("DISPLAY"):
                env.setdefault("MUJOCO_GL", "egl")
        return env

    def status(self, status: Any) -> None:
        """A status the launcher received: the learner's numbers go into the recording."""
        if self.logger is None or self._failed or getattr(status, "role", "") != "learner":
            return
        i = status.info
        try:
            self.logger.learner(i.ingested, {"utd": i.utd, "ingested": i.ingested, "version": i.version,
                                             "grad_steps_per_s": i.grad_steps_per_s})
        except Exception as exc:  # noqa: BLE001 - the view never ends a run
            self._failed = True
            print(f"khgrl up: Rerun view of the learner off: {exc!r}", file=sys.stderr, flush=True)

    def __exit__(self, *exc: Any) -> None:
        if self.logger is not None:
            try:
                self.logger.rec.flush(timeout_sec=3.0)
                self.logger.rec.disconnect()
            except Exception as err:  # noqa: BLE001
                print(f"khgrl up: Rerun view: {err!r}", file=sys.stderr, flush=True)
        if self.sink is not None:
            self.sink.send_signal(signal.SIGTERM)  # (a file sink has written what arrived)
            try:
                self.sink.wait(SINK_STOP_S)
            except subprocess.TimeoutExpired:
                self.sink.kill()
                self.sink.wait(5)
            if self.spec.kind == "file":
                print(f"khgrl up: Rerun recording in {self.spec.file}", flush=True)
        if self._out is not None:
            self._out.close()
