"""``--demos lerobot:PATH``: the spec, the resampling, and the errors for bad datasets (datasets written by
LeRobot's own writer)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from khgrl.common.lerobot.demos import DemoSpec, LeRobotDemoError, load_lerobot_demos, parse_spec, resample
from khgrl.common.tasks.api import TaskError, load_task

from lerobot_data import write_state_dataset

OWN = "khgrl.deploy.examples.own_task:make_task"


def _path(u: np.ndarray) -> np.ndarray:
    """A smooth 3-D path over the phase u in [0, 1]."""
    return np.stack([u, np.sin(np.pi * u), u**2], axis=1)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """4 episodes of 12, 30, 45 and 7 frames of [t, x, y, z] (x, y, z = _path of the episode's phase)."""
    eps = [np.concatenate([np.arange(f)[:, None] / 10, _path(np.linspace(0, 1, f))], axis=1) for f in (12, 30, 45, 7)]
    return write_state_dataset(tmp_path_factory.mktemp("lr") / "ds", eps)


def test_parse_spec() -> None:
    assert parse_spec("lerobot:/d") == DemoSpec(Path("/d"))
    spec = parse_spec("lerobot:/d?feature=observation.pos&dims=1:4&n=50")
    assert spec == DemoSpec(Path("/d"), "observation.pos", (1, 4), 50)
    assert parse_spec(spec.text()) == spec and parse_spec("lerobot:d?dims=:2").dims == (None, 2)
    for bad, what in [("lerobot:/d?feat=x", "unknown key 'feat'"), ("lerobot:/d?dims=3", "not a slice"),
                      ("lerobot:/d?n=1", "n='1'"), ("lerobot:", "no dataset folder"), ("/d", "not a LeRobot")]:
        with pytest.raises(LeRobotDemoError, match=what):
            parse_spec(bad)


def test_resample_is_linear_over_the_phase() -> None:
    pts = np.array([[0.0, 10.0], [1.0, 30.0], [4.0, 20.0]])  # frames at u = 0, 0.5, 1
    out = resample(pts, 5)  # s = 0, .25, .5, .75, 1
    np.testing.assert_allclose(out, [[0, 10], [0.5, 20], [1, 30], [2.5, 25], [4, 20]])


def test_episodes_resampled_to_the_tasks_grid(dataset: Path) -> None:
    demos = load_lerobot_demos(f"lerobot:{dataset}?dims=1:4", n=40, o=3)
    assert demos.shape == (4, 40, 3)
    truth = _path(np.linspace(0, 1, 40))
    for m, frames in enumerate((12, 30, 45, 7)):
        np.testing.assert_allclose(demos[m, [0, -1]], truth[[0, -1]], atol=1e-6)  # ends kept exactly
        err = np.abs(demos[m] - truth).max()
        assert err < 1.5 * np.pi**2 / 8 / (frames - 1) ** 2 + 1e-6, (frames, err)  # linear interpolation's bound
    assert load_lerobot_demos(f"lerobot:{dataset}?dims=1:4&n=9").shape == (4, 9, 3)  # n= wins
    assert load_lerobot_demos(f"lerobot:{dataset}").shape == (4, 45, 4)  # default: the longest episode, all dims


def test_lerobot_demos_replace_a_tasks_own(dataset: Path) -> None:
    task = load_task(OWN, f"lerobot:{dataset}?dims=-3:")
    assert task.demos.shape == (4, 200, 3)  # the own task's N = 200, O = 3
    with pytest.raises(TaskError, match=r"gives 4 values per frame, the task's positions have O = 3"):
        load_task(OWN, f"lerobot:{dataset}")


@pytest.mark.parametrize("query, message", [
    ("?feature=observation.velocity", "no feature 'observation.velocity'; its numeric features: observation.state"),
    ("?dims=0:2", "gives 2 values per frame"),
    ("?dims=2:9", "outside feature 'observation.state' of width 4"),
])
def test_bad_feature_or_width(dataset: Path, query: str, message: str) -> None:
    with pytest.raises(LeRobotDemoError, match=message):
        load_lerobot_demos(f"lerobot:{dataset}{query}", n=20, o=3)


def test_not_a_dataset(tmp_path: Path) -> None:
    (tmp_path / "plain").mkdir()
    with pytest.raises(LeRobotDemoError, match="not a LeRobot dataset \\(no meta/info.json"):
        load_lerobot_demos(f"lerobot:{tmp_path / 'plain'}")
    assert not (tmp_path / "plain" / "meta").exists()  # the loader never saw it: nothing created, no hub asked
    with pytest.raises(LeRobotDemoError, match="no such LeRobot dataset folder"):
        load_lerobot_demos(f"lerobot:{tmp_path / 'missing'}")
    assert not (tmp_path / "missing").exists()
    broken = tmp_path / "broken"
    (broken / "meta").mkdir(parents=True)
    (broken / "meta" / "info.json").write_text("{}")
    with pytest.raises(LeRobotDemoError, match="LeRobot's loader cannot read it"):
        load_lerobot_demos(f"lerobot:{broken}")


def test_short_or_non_finite_episodes_refused(tmp_path: Path) -> None:
    ok = _path(np.linspace(0, 1, 5))
    short = write_state_dataset(tmp_path / "short", [ok, ok[:1]])
    with pytest.raises(LeRobotDemoError, match="episode 1 has 1 frame\\(s\\); a demonstration needs at least 2"):
        load_lerobot_demos(f"lerobot:{short}")
    nan = ok.copy()
    nan[3, 2] = np.nan
    bad = write_state_dataset(tmp_path / "nan", [ok, nan])
    with pytest.raises(LeRobotDemoError, match="episode 1, frame 3, entry 2 of the selected feature is not finite"):
        load_lerobot_demos(f"lerobot:{bad}")


def test_khgrl_up_refuses_a_bad_source_in_one_line(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "up", "--task", OWN, "--demos",
                           f"lerobot:{tmp_path}", "--run-dir", str(tmp_path / "run")], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "not a LeRobot dataset (no meta/info.json" in proc.stdout + proc.stderr
    assert not (tmp_path / "run").exists()
