"""Mistakes in a user's scene (issue 36, "the newcomer's friction"): bad via-points are one line and exit 2 from
``khgrl up`` before any process starts, as the README promises for task mistakes.

Before: ``Scene.via_points`` was first called by the actor at its first reset, so a NaN, a wrong size or a phase
outside [0, 1] failed after the router, learner and actor had started, with a 28-line traceback and a failed run
directory; a via-point outside the workspace box was accepted silently.
"""

from __future__ import annotations

import shutil
import subprocess

import pytest

from helpers import REPO
from launch import UP, _env

pytestmark = pytest.mark.integration

BAD_TASKS = '''
from dataclasses import replace

import numpy as np
from khgrl.common.tasks.scene import ViaPoint
import scene_point_task as base


def _with(via):
    task = base.make_task()
    return replace(task, scene=replace(task.scene, via_points=via))


def nan():
    return _with(lambda obs: [ViaPoint(1.0, (np.nan, 0.5))])


def size():
    return _with(lambda obs: [ViaPoint(1.0, (0.5, 0.5, 0.5))])


def phase():
    return _with(lambda obs: [ViaPoint(1.5, obs[2:4])])


def outside():
    return _with(lambda obs: [ViaPoint(1.0, (1.4, 0.5))])
'''

CASES = {"nan": "position must be 2 finite values", "size": "position must be 2 finite values",
         "phase": "phase must be in [0, 1]", "outside": "lies outside the workspace box"}


@pytest.fixture(scope="module")
def task_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad_via")
    shutil.copy(REPO / "tests" / "scene_point_task.py", d / "scene_point_task.py")
    (d / "bad_via.py").write_text(BAD_TASKS)
    return d


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_via_points_are_one_line_and_exit_2_before_any_process(task_dir, case):
    run_dir = task_dir / f"run-{case}"
    proc = subprocess.run([*UP, "--task", f"bad_via:{case}", "--human", "none", "--episodes", "1",
                           "--run-dir", str(run_dir), "--no-progress"], cwd=task_dir, env=_env(),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and CASES[case] in lines[0] and "Scene.via_points" in lines[0], proc.stderr
    assert not run_dir.exists() and "khgrl up: run" not in proc.stdout  # nothing written, nothing started
