"""The README's own-task example, copied as a user would into a folder outside the repository, runs through
``khgrl up`` and ``khgrl eval``; from that folder only the ``khgrl`` package is importable (the repository's
folders are not top-level packages)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import REPO


def readme_task() -> str:
    """The first Python block of the README's "Bring your own task" section."""
    text = (REPO / "README.md").read_text()
    section = text[text.index("## Bring your own task"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def _run(args: list[str], cwd: Path, timeout: float) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error", "PYTHONPATH": ""}
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_the_readme_task_runs_from_a_scratch_folder(tmp_path: Path) -> None:
    code = readme_task()
    assert "from khgrl.task import" in code
    (tmp_path / "mytask.py").write_text(code)
    gone = _run(["-c", "import common"], tmp_path, 60)
    assert gone.returncode == 1 and "No module named 'common'" in gone.stderr
    up = _run(["-m", "khgrl.deploy.cli", "up", "--task", "mytask:make_task", "--human", "none", "--episodes", "1",
               "--run-dir", "runs/mine", "--no-progress", "--seed", "0"], tmp_path, 240)
    assert up.returncode == 0, up.stdout[-2000:] + up.stderr[-2000:]
    assert (tmp_path / "runs/mine/actor-a0/episodes.csv").read_text().count("\n") == 2  # header + 1 episode
    ev = _run(["-m", "khgrl.deploy.cli", "eval", "runs/mine", "--episodes", "1"], tmp_path, 120)
    assert ev.returncode == 0, ev.stdout[-2000:] + ev.stderr[-2000:]
    assert (tmp_path / "runs/mine/eval/eval.csv").is_file()
