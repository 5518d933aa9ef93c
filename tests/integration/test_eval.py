"""``khgrl eval`` (deploy/tools/evaluate.py) and the example task (deploy/examples/own_task.py).

Most tests evaluate a run directory made here without processes: a ``config.json`` naming the example task
and a learner checkpoint holding an untrained TQC on the task's spaces (the same ``model.zip`` layout the
learner writes). The end-to-end test trains the example task with ``khgrl up`` for 2 episodes and evaluates
that run (marked ``integration``).
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from khgrl.common.config.settings import RunConfig, TQCSettings, write_run_config
from khgrl.common.kmp.scale import ScaleModel
from khgrl.common.tasks.api import load_task
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.deploy.cli import main as khgrl
from khgrl.deploy.examples.own_task import BOX_HIGH, BOX_LOW, GOAL, PointRobot3D, box_entry, lift_over_box, make_task
from khgrl.deploy.tools.evaluate import EvalError, evaluate, free_path

from helpers import REPO, SMALL, kill_pids, pid_alive, read_json

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # the GIF's renderer (pygame, offscreen)

SPEC = "khgrl.deploy.examples.own_task:make_task"
NET = (32, 32)


def _fake_run(run_dir: Path, task: str = SPEC, seed: int = 0) -> Path:
    """A run directory with config.json and an untrained checkpoint of ``task`` (what the learner saves)."""
    from sb3_contrib import TQC

    cfg = RunConfig(run_dir=str(run_dir), task=task, seed=seed, tqc=TQCSettings(net_arch=NET))
    write_run_config(run_dir, cfg, {"run": "evaltest"})
    env = KGRLEnv(load_task(cfg.task_spec))
    ckpt = run_dir / "learner" / "checkpoint"
    ckpt.mkdir(parents=True)
    TQC("MlpPolicy", env, **cfg.tqc.sb3_kwargs(seed)).save(ckpt / "model.zip")
    (ckpt / "state.json").write_text(json.dumps({"format": 2, "total_ingested": 0, "version": 0}))
    return run_dir


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return _fake_run(tmp_path_factory.mktemp("eval") / "run")


def _csv_rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


# ------------------------------------------------------------------------------------ the example task
def test_example_task_passes_gymnasium_checks():
    from gymnasium.utils.env_checker import check_env

    check_env(PointRobot3D(), skip_render_check=True)
    env = KGRLEnv(make_task())
    check_env(env, skip_render_check=True)
    assert env.observation_space.shape == (7,) and env.action_space.shape == (3,) and env.horizon == 200
    d = env.descriptor(SPEC)
    assert d.view_axes == (0, 1) and d.third == 2 and [s["name"] for s in d.shapes] == ["keep-out", "start", "goal"]
    assert d.demos.shape == (6, 200, 3)


def _roll(env: KGRLEnv, act, human=None) -> tuple[bool, int]:
    """(success, blocked steps) of one episode with a constant action (and the scripted human if given)."""
    env.reset(seed=0)
    blocked, done, info = 0, False, {}
    while not done:
        if human is not None:
            env.set_correction(human(env.mapping.mean(env.t)))
        _, _, term, trunc, info = env.step(np.asarray(act, dtype=np.float32))
        blocked += info["blocked"]
        done = term or trunc
    return info["success"], blocked


def test_example_task_needs_a_lift_over_the_box():
    """The KMP mean runs into the box (blocked, no success); lifting (an action in z, or the scripted human) gets
    over it to the goal; the robot never enters the box."""
    env = KGRLEnv(make_task())
    ok, blocked = _roll(env, [0, 0, 0])
    assert not ok and blocked > 50
    assert _roll(env, [0, 0, 1]) == (True, 0)
    assert _roll(env, [0, 0, 0], human=lift_over_box) == (True, 0)
    assert np.linalg.norm(env.position - GOAL) <= 0.05
    inside = [np.all((p > BOX_LOW) & (p < BOX_HIGH)) for p in env.trail]
    assert not any(inside)


def test_box_entry_stops_at_the_face():
    p, q = np.array([0.3, 0.5, 0.1]), np.array([0.5, 0.5, 0.1])
    assert box_entry(p, q) == pytest.approx(0.5)
    assert box_entry(p, np.array([0.35, 0.5, 0.1])) is None  # stops short of it
    assert box_entry(np.array([0.3, 0.5, 0.4]), np.array([0.7, 0.5, 0.4])) is None  # over it
    robot = PointRobot3D()
    robot.reset()
    robot.robot = np.array([0.39, 0.5, 0.1])  # 0.01 before the face, at most 0.02 per step
    _, r, term, _, info = robot.step(q)
    assert info["blocked"] and r == -10.0 and not term and robot.robot[0] < BOX_LOW[0]


# ------------------------------------------------------------------------------------ khgrl eval
def test_eval_writes_csv_and_gif_and_never_overwrites(run_dir, capsys):
    gif = run_dir / "eval" / "ep1.gif"
    rc = khgrl(["eval", str(run_dir), "--episodes", "3", "--seed", "5", "--gif", str(gif)])
    out = capsys.readouterr().out
    assert rc == 0, out
    rows = _csv_rows(run_dir / "eval" / "eval.csv")
    assert [int(r["episode"]) for r in rows] == [1, 2, 3] and [int(r["seed"]) for r in rows] == [5, 6, 7]
    for r in rows:
        assert float(r["return"]) == pytest.approx(float(r["env_return"]) + float(r["action_cost"]), abs=1e-3)
        assert r["success"] in ("True", "False") and 1 <= int(r["steps"]) <= 200
    assert "success " in out and " ± " in out and "point-3d" in out
    from PIL import Image

    with Image.open(gif) as im:
        assert im.n_frames > 1 and im.size[0] > 100
        frames = []
        for k in (0, im.n_frames - 1):
            im.seek(k)
            frames.append(np.asarray(im.convert("RGB"), dtype=np.int16))
    assert np.abs(frames[0] - frames[1]).sum() > 0  # the robot moved
    # a second evaluation keeps the first one's files
    assert khgrl(["eval", str(run_dir), "--episodes", "1", "--gif", str(gif)]) == 0
    assert len(_csv_rows(run_dir / "eval" / "eval.csv")) == 3
    assert len(_csv_rows(run_dir / "eval" / "eval-2.csv")) == 1
    assert (run_dir / "eval" / "ep1-2.gif").is_file()


def test_eval_is_deterministic_and_uses_the_learned_scale(run_dir, tmp_path):
    a = evaluate(run_dir, episodes=1, csv_path=tmp_path / "a.csv")
    b = evaluate(run_dir, episodes=1, csv_path=tmp_path / "b.csv")
    assert a.episodes == b.episodes and a.scale.startswith("L0")
    model = ScaleModel(5.0, dim=3)
    model.update(np.full((20, 3), 40.0), np.linspace(0.3, 0.7, 20))
    (run_dir / "actor-a0").mkdir()
    try:
        (run_dir / "actor-a0" / "scale_model.json").write_text(json.dumps(model.to_dict()))
        c = evaluate(run_dir, episodes=1, csv_path=tmp_path / "c.csv")
        assert c.scale.startswith("learned by actor-a0")
        assert c.episodes[0].action_cost != a.episodes[0].action_cost  # L scales the policy's action
        (run_dir / "actor-a0" / "scale_model.json").write_text(json.dumps(ScaleModel(5.0, dim=2).to_dict()))
        with pytest.raises(EvalError, match="2 outputs, the task has 3"):
            evaluate(run_dir, episodes=1, csv_path=tmp_path / "d.csv")
    finally:
        (run_dir / "actor-a0" / "scale_model.json").unlink()
        (run_dir / "actor-a0").rmdir()


def test_eval_finds_the_task_module_and_demos_where_khgrl_up_ran(run_dir, tmp_path, capsys):
    """A run started in another directory (runtime ``cwd`` in config.json) with a task module and a relative
    ``--demos`` file there: eval finds both from anywhere."""
    from khgrl.common.tasks.demos import save_demos
    from khgrl.deploy.examples.own_task import make_demos

    home = tmp_path / "home"
    home.mkdir()
    (home / "evaltask_h3.py").write_text("from khgrl.deploy.examples.own_task import make_task\n")
    save_demos(home / "mine.npz", make_demos(m=4, seed=3))
    run = tmp_path / "run"
    write_run_config(run, RunConfig(run_dir=str(run), task="evaltask_h3:make_task", demos="mine.npz",
                                    tqc=TQCSettings(net_arch=NET)), {"cwd": str(home)})
    ev = evaluate(run, checkpoint=run_dir / "learner", episodes=1)
    assert ev.spec == "evaltask_h3:make_task" and len(ev.episodes) == 1 and ev.csv == run / "eval" / "eval.csv"


def test_free_path(tmp_path):
    p = tmp_path / "eval.csv"
    assert free_path(p) == p
    p.write_text("x")
    assert free_path(p) == tmp_path / "eval-2.csv"
    (tmp_path / "eval-2.csv").write_text("x")
    assert free_path(p) == tmp_path / "eval-3.csv"


def _one_error_line(capsys, argv: list[str], expect: str) -> None:
    assert khgrl(["eval", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("khgrl eval: error: ") and expect in err, err


def test_eval_bad_inputs_exit_2_with_one_line(run_dir, tmp_path, capsys):
    _one_error_line(capsys, [str(tmp_path / "nowhere")], "no config.json")
    empty = tmp_path / "empty"
    write_run_config(empty, RunConfig(run_dir=str(empty), task=SPEC), {})
    _one_error_line(capsys, [str(empty)], "no learner checkpoint")
    _one_error_line(capsys, [str(run_dir), "--checkpoint", str(tmp_path / "none")], "no model.zip")
    with pytest.raises(SystemExit) as usage:  # the parser's usage error, before anything loads
        khgrl(["eval", str(run_dir), "--episodes", "0"])
    assert usage.value.code == 2 and "--episodes: must be >= 1, got 0" in capsys.readouterr().err
    bad = tmp_path / "badtask"
    write_run_config(bad, RunConfig(run_dir=str(bad), task="no_such_module:make_task"), {})
    _one_error_line(capsys, [str(bad), "--checkpoint", str(run_dir / "learner")], "cannot import 'no_such_module'")
    # a checkpoint of another task (the passage world: 5 observations, 2 actions) does not fit this one
    other = _fake_run(tmp_path / "passage", task="")
    _one_error_line(capsys, [str(run_dir), "--checkpoint", str(other / "learner" / "checkpoint")],
                    "does not fit this task's spaces (observation 7, action 3)")
    (tmp_path / "junk.zip").write_text("not a zip")
    _one_error_line(capsys, [str(run_dir), "--checkpoint", str(tmp_path / "junk.zip")], "cannot read the model")


# ------------------------------------------------------------------------------------ end to end
def _khgrl(*args: str, timeout: float, cwd: Path = REPO) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RUST_LOG": "error", "SDL_VIDEODRIVER": "dummy"}
    return subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.integration
@pytest.mark.timeout(400)
def test_khgrl_up_on_the_example_task_then_eval(tmp_path):
    """The example task trained by the real processes for 2 episodes (the scripted human lifts the robot over the
    box in episode 1), then ``khgrl eval`` on that run through the ``khgrl`` command."""
    run = tmp_path / "run"
    try:
        up = _khgrl("up", "--task", SPEC, "--episodes", "2", "--learning-starts", "100", "--human-episodes", "1",
                    *SMALL, "--no-progress", "--run-dir", str(run), timeout=300)
    finally:
        if (run / "pids.json").exists():
            kill_pids([p for p in read_json(run / "pids.json")["children"].values() if pid_alive(p)])
    assert up.returncode == 0, f"{up.stdout}\n{up.stderr}"
    assert len(_csv_rows(run / "actor-a0" / "episodes.csv")) == 2
    ev = _khgrl("eval", str(run), "--episodes", "2", "--gif", str(tmp_path / "ep.gif"), timeout=200)
    assert ev.returncode == 0, f"{ev.stdout}\n{ev.stderr}"
    assert len(_csv_rows(run / "eval" / "eval.csv")) == 2 and (tmp_path / "ep.gif").is_file()
    assert "point-3d" in ev.stdout and "success" in ev.stdout
