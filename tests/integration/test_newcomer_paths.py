"""What a new user met in issue 36 ("the newcomer's friction"), each against the real command or process.

* ``khgrl experiment --ray local`` could not import a task module that the same command without ``--ray``
  imports: the run's ``khgrl up`` started in the worker's scratch directory, without the head's working directory
  on its path (the reason was only in experiment.json). Here the worker's task itself runs a user's module.
* ``khgrl view RUN --out missing/dir/x.rrd`` ended in a traceback; ``khgrl eval --scenes 0`` loaded for 12 s
  before saying the argument is wrong.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import pytest

from helpers import REPO
from launch import _env

pytestmark = pytest.mark.integration

CLI = [sys.executable, "-m", "khgrl.deploy.cli"]


@pytest.mark.timeout(120)
def test_a_ray_worker_runs_a_task_module_from_the_heads_directory(tmp_path):
    """Before: ``run_on_worker`` ran the run's command with the scratch directory as its working directory and the
    worker's environment only: ``task 'scene_point_task:make_task': no module named scene_point_task``. (The
    command here imports the task module as ``khgrl up --task`` does and prints an episode line, so that the test
    takes seconds; test_experiment_ray.py runs whole ``khgrl up`` runs on a real cluster.)"""
    from khgrl.deploy.experiments.ray_worker import khgrl_identity, run_on_worker

    head = tmp_path / "head"
    head.mkdir()
    shutil.copy(REPO / "tests" / "scene_point_task.py", head / "scene_point_task.py")
    run_dir = str(head / "out" / "r")
    code = ("import sys; from khgrl.common.tasks.api import load_task; load_task('scene_point_task:make_task'); "
            "print('[a0] episode 1: ok', sys.argv[1])")
    events = list(run_on_worker("r", [sys.executable, "-c", code, run_dir], run_dir, khgrl_identity(), [str(head)]))
    end = events[-1]
    assert end["event"] == "end" and end["returncode"] == 0, end["log_tail"]
    assert [e["episode"] for e in events if e["event"] == "episode"] == [1]
    assert str(head) not in end["log_tail"]  # the run directory was the worker's scratch one, as for a real run


def test_view_into_a_missing_folder_and_eval_of_zero_scenes_are_one_line_at_once(tmp_path):
    """Before: a FileNotFoundError traceback from Rerun's writer; ``--scenes 0`` refused only after torch and the
    run's task were loaded."""
    run = tmp_path / "run" / "actor-a0" / "steps"
    run.mkdir(parents=True)
    (run / "episode-000001.npz").write_bytes(b"")
    view = subprocess.run([*CLI, "view", str(tmp_path / "run"), "--out", str(tmp_path / "no" / "such" / "x.rrd")],
                          capture_output=True, text=True, timeout=120, env=_env())
    assert view.returncode == 2 and view.stderr.count("\n") == 1 and "no such folder" in view.stderr, view.stderr
    t0 = time.monotonic()
    ev = subprocess.run([*CLI, "eval", str(tmp_path / "run"), "--scenes", "0"], capture_output=True, text=True,
                        timeout=120, env=_env())
    took = time.monotonic() - t0
    assert ev.returncode == 2 and "--scenes: must be >= 1" in ev.stderr and "Traceback" not in ev.stderr, ev.stderr
    assert "torch" not in ev.stderr
    print(f"khgrl eval --scenes 0 answered in {took:.2f} s")


def test_no_spacemouse_is_said_before_anything_starts(tmp_path):
    """Before: ``khgrl up --human spacemouse`` started every process and failed after 36 s; ``khgrl human
    spacemouse`` blamed the display or hidapi. Here the kernel's device list is an empty folder (no SpaceMouse),
    then one that lists a SpaceMouse Compact (USB 256f:c635)."""
    from khgrl.human_bridge.hid_devices import HID_DEVICES_ENV, connected_spacemice

    devices = tmp_path / "hid"
    devices.mkdir()
    env = {**_env(no_display=True), HID_DEVICES_ENV: str(devices)}
    up = subprocess.run([*CLI, "up", "--human", "spacemouse", "--episodes", "1", "--run-dir", str(tmp_path / "run")],
                        capture_output=True, text=True, timeout=120, env=env)
    assert up.returncode == 2 and "no SpaceMouse found" in up.stderr and up.stderr.count("\n") == 1, up.stderr
    assert not (tmp_path / "run").exists()
    client = subprocess.run([*CLI, "human", "spacemouse", "--run", "r", "--connect", "tcp/127.0.0.1:1"],
                            capture_output=True, text=True, timeout=120, env=env)
    assert client.returncode == 3 and "no SpaceMouse found" in client.stderr, client.stderr
    assert connected_spacemice(str(devices)) == []
    (devices / "0003:256F:C635.0001").mkdir()
    assert connected_spacemice(str(devices)) == ["SpaceMouseCompact"]
