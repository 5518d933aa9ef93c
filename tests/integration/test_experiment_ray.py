"""khgrl experiment --ray: a 2-run grid on a real local Ray cluster (a head with no CPUs and one worker node, so
every run lands on the worker) gives the same results as the same grid run locally with --jobs 2; a finished run
folder already in OUT is kept and an unfinished one is redone."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from khgrl.common.delivery.transport import free_port
from khgrl.deploy.experiments.experiment import ExperimentConfig, run_is_done

from helpers import REPO, SMALL_UP

RAY = str(Path(sys.executable).with_name("ray"))
GRID = ["--scenarios", "low_cov", "--methods", "khgrl", "kgrl", "--seeds", "0", "--episodes", "2",
        "--human-episodes", "2", "--no-progress", "--timeout", "240", SMALL_UP]
# Ray's token authentication (its default) with a token of this test's: the cluster, the workers and the driver
# (khgrl experiment) get it from the environment, not from the user's ~/.ray/auth_token
_AUTH = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
NAMES = [f"low_cov-{m}-seed0" for m in ("khgrl", "kgrl")]  # (one kept as it is, one redone on the worker)


def _ours(temp_dir: Path) -> list[int]:
    """PIDs of the processes of our Ray cluster: every one names its temporary directory on its command line."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and str(temp_dir).encode() in (proc / "cmdline").read_bytes():
                pids.append(int(proc.name))
        except OSError:
            continue
    return pids


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture
def ray_cluster():
    """A head (0 CPUs: it runs nothing) and one worker node (2 CPUs), each a ``ray start --block`` of its own;
    stopped at the end by PID (theirs and every process naming the cluster's temporary directory)."""
    temp_dir = Path(tempfile.mkdtemp(prefix="kray-", dir="/tmp"))  # short: Ray's socket paths must fit 107 bytes
    port = free_port()

    def common() -> list[str]:  # each node's agents on ports of their own (the defaults collide on one host)
        return ["--object-store-memory=100000000", "--disable-usage-stats", "--block",
                f"--dashboard-agent-listen-port={free_port()}", f"--metrics-export-port={free_port()}",
                f"--runtime-env-agent-port={free_port()}"]

    env = {**os.environ, **_AUTH, "RAY_USAGE_STATS_ENABLED": "0"}
    logs = [open(temp_dir / f"{n}.log", "w") for n in ("head", "worker")]
    procs = [subprocess.Popen([RAY, "start", "--head", f"--port={port}", "--num-cpus=0", "--include-dashboard=false",
                               f"--ray-client-server-port={free_port()}", f"--temp-dir={temp_dir}", *common()],
                              stdout=logs[0], stderr=subprocess.STDOUT, env=env, start_new_session=True)]
    try:
        deadline = time.monotonic() + 60
        while not _port_open(port):
            assert time.monotonic() < deadline and procs[0].poll() is None, (temp_dir / "head.log").read_text()
            time.sleep(0.2)
        procs.append(subprocess.Popen([RAY, "start", f"--address=127.0.0.1:{port}", "--num-cpus=2",
                                       f"--temp-dir={temp_dir / 'w'}", *common()],
                                      stdout=logs[1], stderr=subprocess.STDOUT, env=env, start_new_session=True))
        yield f"127.0.0.1:{port}"
    finally:
        for p in reversed(procs):  # the worker first; --block stops its node's processes on SIGTERM
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for pid in _ours(temp_dir):  # whatever is left of the cluster
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for log in logs:
            log.close()
        leftover = _ours(temp_dir)
        shutil.rmtree(temp_dir, ignore_errors=True)
        assert not leftover, f"Ray processes left behind: {leftover}"


def _experiment(out: Path, *extra: str) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "khgrl.deploy.cli", "experiment", "--out", str(out), *GRID, *extra]
    return subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=300, env={**os.environ, **_AUTH})


def _untimed_csv(run: Path) -> list[list[str]]:
    """Columns 1-15 of a run's episodes.csv (``cut -d, -f1-15``: the rest measure time)."""
    return [line.split(",")[:15] for line in (run / "actor-a0" / "episodes.csv").read_text().splitlines()]


def _table(out: Path) -> list[str]:
    report = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "report", str(out), "--out", str(out / "rep")],
                            cwd=REPO, capture_output=True, text=True, timeout=200)
    assert report.returncode == 0, report.stdout + report.stderr
    return [line for line in report.stdout.splitlines() if line.startswith("|")]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(800)
def test_ray_grid_matches_the_local_grid_and_resumes(tmp_path, ray_cluster):
    local, remote = tmp_path / "local", tmp_path / "ray"
    first = _experiment(local, "--jobs", "2")
    assert first.returncode == 0, first.stdout + first.stderr
    # in the Ray OUT: a finished run (kept as it is) and an interrupted one (redone from scratch)
    kept = remote / "low_cov-kgrl-seed0"
    shutil.copytree(local / kept.name, kept)
    stamp = (kept / "summary.json").stat().st_ino
    half = remote / "low_cov-khgrl-seed0"
    half.mkdir(parents=True)
    (half / "leftover.txt").write_text("half a run")

    proc = _experiment(remote, "--ray", ray_cluster, "--ray-cpus", "2")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "low_cov-kgrl-seed0: finished before, not redone" in proc.stdout
    assert "running on" in proc.stdout
    assert (kept / "summary.json").stat().st_ino == stamp and not (half / "leftover.txt").exists()
    assert sorted(p.name for p in remote.iterdir() if p.is_dir()) == sorted(NAMES)  # no temporary unpacking left
    runs = json.loads((remote / "experiment.json").read_text())["runs"]
    cfg = ExperimentConfig(episodes=2)
    for name in NAMES:
        assert run_is_done(local / name, cfg) and run_is_done(remote / name, cfg), name
        assert runs[name]["status"] == "done", runs[name]
        assert _untimed_csv(local / name) == _untimed_csv(remote / name), name
        if name != kept.name:
            assert runs[name]["node"] and runs[name]["ray"] == ray_cluster and runs[name]["wall_time_s"] > 0
            assert (remote / name / "experiment.log").read_text().count("[a0] episode") == 2
    assert _table(local) == _table(remote) and len(_table(local)) >= 4  # header, rule, khgrl and kgrl rows
