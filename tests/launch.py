"""``khgrl up`` from tests: a run in the background (:class:`Launcher`) or to its end (:func:`_run`), its files."""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from helpers import REPO, SMALL, endpoint_pattern, kill_pids, pid_alive, pids_matching, read_json, wait_for

__all__ = ["UP", "FAST", "KGRL", "HUMAN_EPISODE", "Launcher", "_env", "_run", "_rows", "_ingested"]

UP = [sys.executable, "-m", "khgrl.deploy.cli", "up"]


def up_with_actor_certs(ids) -> list[str]:
    """``khgrl up`` that also makes ``--secure`` certificates for the actor ids ``ids`` (attackers in tests), made
    by the run's CA like every other identity (``khgrl.deploy.run.secure.EXTRA_IDS``)."""
    return [sys.executable, "-c", "import sys; from khgrl.deploy import cli; from khgrl.deploy.run import secure; "
            f"secure.EXTRA_IDS = (*secure.EXTRA_IDS, *[('actor', a) for a in {tuple(ids)!r}]); "
            "sys.exit(cli.main(sys.argv[1:]))", "up"]
FAST = ["--scenario", "low_cov", "--learning-starts", "64", "--no-progress", *SMALL]  # (SMALL: helpers.py)
KGRL = [*FAST, "--method", "kgrl", "--human", "none"]
HUMAN_EPISODE = 3  # the scripted human helps in episode 3 of the run only


def _env(no_display: bool = False) -> dict:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RUST_LOG", "error")
    if no_display:
        for name in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"):
            env.pop(name, None)
    return env


class Launcher:
    """One ``khgrl up`` in the background, its stdout/stderr in files beside the run directory."""

    def __init__(self, tmp: Path, run_dir: Path, *args: str, env: dict | None = None) -> None:
        self.run_dir = run_dir
        self.found: dict[str, int] = {}
        self.out_path, self.err_path = tmp / f"{run_dir.name}.stdout", tmp / f"{run_dir.name}.stderr"
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen([*UP, "--run-dir", str(run_dir), *args], cwd=REPO, env=env or _env(),
                                         stdout=out, stderr=err, start_new_session=True)

    @property
    def stdout(self) -> str:
        return self.out_path.read_text()

    @property
    def stderr(self) -> str:
        return self.err_path.read_text()

    def children(self, timeout: float = 60.0) -> dict[str, int]:
        """The children's PIDs from pids.json, once the launcher wrote it (a launcher without pids.json: the
        processes started with its router endpoint, found by their command lines)."""
        path = self.run_dir / "pids.json"
        started = re.compile(r"khgrl up: run \S+ on (\S+);")
        wait_for(lambda: path.exists() or started.search(self.stdout), timeout, "khgrl up to start its processes")
        if path.exists():
            assert read_json(path)["launcher"] == self.proc.pid
            self.found = read_json(path)["children"]
        else:
            time.sleep(2.0)
            self.found = {f"pid{p}": p for p in pids_matching(endpoint_pattern(started.search(self.stdout).group(1)))}
        return self.found

    def wait_line(self, text: str, timeout: float) -> None:
        def seen() -> bool:
            assert self.proc.poll() is None, f"khgrl up exited {self.proc.returncode}\n{self.stdout}\n{self.stderr}"
            return text in self.stdout

        wait_for(seen, timeout, f"{text!r} on khgrl up's stdout")

    def cleanup(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        path = self.run_dir / "pids.json"
        pids = set(self.found.values()) | (set(read_json(path)["children"].values()) if path.exists() else set())
        kill_pids([p for p in pids if pid_alive(p)])


def _run(run_dir: Path, *args: str, timeout: float = 240, env: dict | None = None) -> subprocess.CompletedProcess:
    """``khgrl up`` to the end; children left by a launcher killed on timeout are killed by PID."""
    try:
        return subprocess.run([*UP, "--run-dir", str(run_dir), *args], cwd=REPO, env=env or _env(),
                              capture_output=True, text=True, timeout=timeout)
    finally:
        if (run_dir / "pids.json").exists():
            kill_pids([p for p in read_json(run_dir / "pids.json")["children"].values() if pid_alive(p)])


def _rows(run_dir: Path, name: str = "episodes.csv") -> list[dict]:
    with open(run_dir / "actor-a0" / name, newline="") as fh:
        return list(csv.DictReader(fh))


def _ingested(run_dir: Path) -> int:
    """Transitions in the learner's (final) checkpoint."""
    return int(read_json(run_dir / "learner" / "checkpoint" / "state.json")["total_ingested"])


