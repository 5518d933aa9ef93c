"""Nothing deleted that a command did not make, and ``khgrl ready`` honest about what waited (issue 33, defect 8),
with one real ``khgrl up`` (router, learner, actor).

While the run is alive, ``khgrl up --overwrite`` on its directory is refused (exit 2, one line naming what is alive)
and the run goes on untouched; ``khgrl ready`` says that nothing waited for it. Once it has ended, ``khgrl export
--overwrite`` refuses to replace the source run, the folder that holds it, and a folder that looks like a dataset but
holds something else; it replaces a dataset it wrote.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from helpers import REPO, wait_for
from launch import KGRL, Launcher, _env

pytestmark = pytest.mark.integration

CLI = [sys.executable, "-m", "khgrl.deploy.cli"]


def _khgrl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], cwd=REPO, env=_env(), capture_output=True, text=True, timeout=180)


def _tree(path) -> dict:
    return {str(p.relative_to(path)): p.stat().st_size for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.mark.timeout(400)
def test_overwrite_and_export_delete_only_what_they_made_and_ready_says_when_nothing_waited(tmp_path):
    """Before the fix: ``khgrl up --overwrite`` deleted the live run's files and started a second run on them;
    ``khgrl ready`` printed "ready confirmed" with nothing waiting; ``khgrl export --lerobot RUN --overwrite`` and
    ``--lerobot PARENT --overwrite`` deleted the source run (and every run beside it)."""
    runs = tmp_path / "runs"
    up = Launcher(tmp_path, runs / "run", *KGRL, "--episodes", "30", "--seed", "5")
    try:
        up.children(90)
        wait_for(lambda: (runs / "run" / "actor-a0" / "steps").is_dir()
                 and any((runs / "run" / "actor-a0" / "steps").iterdir()), 180, "a first episode's step records")
        again = _khgrl("up", "--run-dir", str(runs / "run"), *KGRL, "--episodes", "1", "--overwrite")
        assert again.returncode == 2, again.stdout + again.stderr
        assert "is still running" in again.stderr and "launcher (pid" in again.stderr, again.stderr
        assert len(again.stderr.strip().splitlines()) == 1, again.stderr
        assert up.proc.poll() is None and (runs / "run" / "config.json").is_file()  # the run goes on, whole
        ready = _khgrl("ready", str(runs / "run"))
        assert ready.returncode == 1 and "nothing was waiting for ready" in ready.stderr, ready.stdout + ready.stderr
        assert "a0: not waiting for ready" in ready.stdout and "confirmed" not in ready.stdout, ready.stdout
        stop = _khgrl("stop", str(runs / "run"))
        assert stop.returncode == 0, stop.stdout + stop.stderr
        up.proc.wait(120)
    finally:
        up.cleanup()
    before = _tree(runs)
    for target in (runs / "run", runs):  # the source run; the folder of runs that holds it
        refused = _khgrl("export", str(runs / "run"), "--lerobot", str(target), "--overwrite")
        assert refused.returncode == 2 and "not replaced" in refused.stderr, refused.stdout + refused.stderr
        assert _tree(runs) == before
    out = tmp_path / "dataset"
    assert _khgrl("export", str(runs / "run"), "--lerobot", str(out)).returncode == 0
    info = json.loads((out / "meta" / "info.json").read_text())
    replaced = _khgrl("export", str(runs / "run"), "--lerobot", str(out), "--overwrite", "--fps", "7")
    assert replaced.returncode == 0, replaced.stdout + replaced.stderr
    assert json.loads((out / "meta" / "info.json").read_text())["fps"] == 7 != info["fps"]
    (out / "notes.txt").write_text("mine")  # a dataset folder that holds something else
    kept = _khgrl("export", str(runs / "run"), "--lerobot", str(out), "--overwrite")
    assert kept.returncode == 2 and "notes.txt" in kept.stderr, kept.stdout + kept.stderr
    assert (out / "notes.txt").read_text() == "mine" and _tree(runs) == before
