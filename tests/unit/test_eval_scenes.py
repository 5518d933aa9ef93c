"""``khgrl eval --scenes K`` (deploy/tools/eval_scenes.py), the Wilson interval
(deploy/tools/intervals.py) and how
``khgrl report`` shows an evaluation over scenes or of one fixed scene (deploy/experiments/summary_table.py).

The evaluations run without processes on a run directory made here: a ``config.json`` naming the task and an
untrained TQC checkpoint on its spaces (the learner's ``model.zip`` layout). The varying task is
tests/scene_point_task.py (a 2-D goal placed at random at each reset); the fixed one the example task.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import pytest
from khgrl.common.config.settings import RunConfig, TQCSettings, write_run_config
from khgrl.common.tasks.api import load_task
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.common.tasks.scene import scene_seed
from khgrl.deploy.cli import main as khgrl
from khgrl.deploy.tools.eval_scenes import FIXED_SCENE_NOTE
from khgrl.deploy.tools.evaluate import evaluate
from khgrl.deploy.tools.intervals import rate_text, wilson_interval

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # the GIF's renderer (pygame, offscreen)

VARYING = "scene_point_task:make_task"
FIXED = "khgrl.deploy.examples.own_task:make_task"


# ------------------------------------------------------------------------------------ Wilson
def _textbook_wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The roots in p of the score test (p_hat - p)^2 = z^2 p (1 - p) / n: a quadratic a p^2 + b p + c = 0."""
    p_hat = k / n
    a, b, c = 1 + z * z / n, -(2 * p_hat + z * z / n), p_hat * p_hat
    root = math.sqrt(b * b - 4 * a * c)
    return (-b - root) / (2 * a), (-b + root) / (2 * a)


@pytest.mark.parametrize("k,n,published", [
    # Newcombe (1998), "Two-sided confidence intervals for the single proportion", Stat. Med. 17, Table II, method 3
    (81, 263, (0.2553, 0.3662)), (15, 148, (0.0624, 0.1605)), (0, 20, (0.0, 0.1611)), (1, 29, (0.0061, 0.1718)),
    (0, 10, None), (10, 10, None), (37, 50, None), (5, 8, None)])
def test_wilson_interval_against_references(k, n, published):
    low, high = wilson_interval(k, n)
    ref = _textbook_wilson(k, n)
    assert low == pytest.approx(ref[0], abs=1e-12) and high == pytest.approx(ref[1], abs=1e-12)
    if published is not None:
        assert (round(low, 4), round(high, 4)) == published
    assert 0.0 <= low <= k / n <= high <= 1.0


def test_wilson_ends_and_text():
    assert wilson_interval(0, 10)[0] == 0.0 and wilson_interval(10, 10)[1] == 1.0
    assert wilson_interval(0, 10)[1] == pytest.approx(0.2775328, abs=1e-7)
    assert rate_text(37, 50) == "37/50 = 74 % (95 % CI 60-84 %, Wilson)"
    assert wilson_interval(37, 50, 0.99)[0] < wilson_interval(37, 50)[0]  # wider at 99 %
    for bad in ((1, 0), (-1, 5), (6, 5)):
        with pytest.raises(ValueError):
            wilson_interval(*bad)


# ------------------------------------------------------------------------------------ khgrl eval --scenes
def _fake_run(run_dir: Path, task: str, seed: int = 0) -> Path:
    """A run directory with config.json and an untrained checkpoint of ``task`` (what the learner saves)."""
    from sb3_contrib import TQC

    cfg = RunConfig(run_dir=str(run_dir), task=task, seed=seed, tqc=TQCSettings(net_arch=(16, 16)))
    write_run_config(run_dir, cfg, {"run": "evalscenes"})
    env = KGRLEnv(load_task(cfg.task_spec))
    ckpt = run_dir / "learner" / "checkpoint"
    ckpt.mkdir(parents=True)
    TQC("MlpPolicy", env, **cfg.tqc.sb3_kwargs(seed)).save(ckpt / "model.zip")
    (ckpt / "state.json").write_text(json.dumps({"format": 2, "total_ingested": 0, "version": 0}))
    return run_dir


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def varying(tmp_path_factory) -> Path:
    return _fake_run(tmp_path_factory.mktemp("scenes") / "run", VARYING, seed=4)


@pytest.fixture(scope="module")
def fixed(tmp_path_factory) -> Path:
    return _fake_run(tmp_path_factory.mktemp("fixed") / "run", FIXED)


def test_scenes_csv_columns_seeds_interval_and_gif(varying, capsys):
    gif = varying / "eval" / "scenes.gif"
    assert khgrl(["eval", str(varying), "--scenes", "5", "--gif", str(gif), "--gif-scenes", "2"]) == 0
    out = capsys.readouterr().out
    rows = _rows(varying / "eval" / "scenes.csv")
    assert list(rows[0]) == ["scene", "seed", "varies", "goal_x", "goal_y", "success", "return", "env_return",
                             "action_cost", "steps", "terminated"]
    assert [int(r["scene"]) for r in rows] == [1, 2, 3, 4, 5]
    assert [int(r["seed"]) for r in rows] == [scene_seed(4, k, stream="eval") for k in range(1, 6)]  # the run's seed
    assert len({(r["goal_x"], r["goal_y"]) for r in rows}) == 5 and all(r["varies"] == "True" for r in rows)
    assert all(0.7 <= float(r["goal_x"]) <= 0.9 and 0.3 <= float(r["goal_y"]) <= 0.7 for r in rows)
    k = sum(r["success"] == "True" for r in rows)
    assert f"success {rate_text(k, 5)}; return " in out and FIXED_SCENE_NOTE not in out
    assert "region: goal x in [0.7, 0.9]" in out and "goal_x=" in out
    assert "frames of scenes 1-2)" in out
    from PIL import Image

    with Image.open(gif) as im:
        frames = im.n_frames
    assert 10 < frames <= 2 * 41  # two scenes of 40 steps, subsampled
    # the same seed: the same scenes (and, the policy being deterministic, the same results); never overwritten
    assert khgrl(["eval", str(varying), "--scenes", "5"]) == 0
    again = _rows(varying / "eval" / "scenes-2.csv")
    assert again == rows
    capsys.readouterr()
    assert khgrl(["eval", str(varying), "--scenes", "2", "--seed", "9"]) == 0
    other = _rows(varying / "eval" / "scenes-3.csv")
    assert [int(r["seed"]) for r in other] == [scene_seed(9, 1, stream="eval"), scene_seed(9, 2, stream="eval")]
    assert other[0]["goal_x"] != rows[0]["goal_x"]


def test_plain_episodes_keep_their_output(varying, fixed, capsys):
    """``--episodes`` as before (episodes reset with SEED + i, eval.csv's columns); on a fixed-scene task the one
    added line is the note."""
    assert khgrl(["eval", str(varying), "--episodes", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].split() == ["episode", "seed", "steps", "return", "env", "r_a", "success"]
    assert [line.split()[:2] for line in out[2:4]] == [["1", "4"], ["2", "5"]]
    assert out[4].startswith("success ") and out[5].startswith("wrote ") and FIXED_SCENE_NOTE not in out
    assert list(_rows(varying / "eval" / "eval.csv")[0]) == ["episode", "seed", "steps", "return", "env_return",
                                                             "action_cost", "success", "terminated"]
    assert khgrl(["eval", str(fixed), "--episodes", "2"]) == 0
    out = [line for line in capsys.readouterr().out.splitlines() if not line.startswith("warning: ")]  # (no L)
    assert out[4].startswith("success ") and out[5] == FIXED_SCENE_NOTE and out[6].startswith("wrote ")
    assert len(out) == 7


def test_scenes_on_a_fixed_scene_task_say_so(fixed, capsys):
    ev = evaluate(fixed, scenes=3)
    assert ev.csv == fixed / "eval" / "scenes.csv" and not ev.varies
    rows = _rows(ev.csv)
    assert list(rows[0]) == ["scene", "seed", "varies", "success", "return", "env_return", "action_cost", "steps",
                             "terminated"]  # no placement columns
    assert {r["varies"] for r in rows} == {"False"} and len({r["return"] for r in rows}) == 1  # one rollout, 3 times
    assert khgrl(["eval", str(fixed), "--scenes", "2", "--csv", str(fixed / "two.csv")]) == 0
    out = capsys.readouterr().out
    assert FIXED_SCENE_NOTE in out and "Wilson" not in out and "one scene (the task does not vary)" in out


def test_scenes_usage_errors(varying, capsys):
    assert khgrl(["eval", str(varying), "--scenes", "2", "--episodes", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not both" in err, err
    for argv, expect in ((["--scenes", "0"], "argument --scenes: must be >= 1"),
                         (["--scenes", "2", "--gif-scenes", "0"], "argument --gif-scenes: must be >= 1")):
        with pytest.raises(SystemExit) as exc:  # the parser's usage error, before anything is loaded (issue 36)
            khgrl(["eval", str(varying), *argv])
        assert exc.value.code == 2 and expect in capsys.readouterr().err


# ------------------------------------------------------------------------------------ khgrl report
EPISODE_FIELDS = ["episode", "steps", "ret", "success", "failure", "action_cost", "obstacle_cost", "passage_cost",
                  "obstacle_steps", "interventions", "intervention_steps", "clipped_steps", "projected_steps",
                  "mean_abs_xi_h", "scale_max", "wall_time"]


def _experiment_run(run: Path, outcomes: list[bool], varies: bool | None, task: str | None = None) -> None:
    """A run of 3 episodes with an evaluation: a scenes CSV (``varies`` True/False) or, with ``varies`` None, an
    eval.csv; ``task``: a config.json naming it."""
    from khgrl.deploy.tools.eval_inputs import EpisodeResult
    from khgrl.deploy.tools.eval_scenes import write_scenes_csv

    (run / "actor-a0").mkdir(parents=True)
    with open(run / "actor-a0" / "episodes.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=EPISODE_FIELDS)
        w.writeheader()
        for e in (1, 2, 3):
            w.writerow({**dict.fromkeys(EPISODE_FIELDS, 0), "episode": e, "ret": 1.0, "success": "True",
                        "scale_max": "1;1"})
    import numpy as np

    np.savez(run / "actor-a0" / "scale.npz", phases=np.linspace(0, 1, 10), table=np.ones((10, 2)))
    eps = [EpisodeResult(episode=i + 1, seed=i, steps=40, ret=1.0, env_return=1.0, action_cost=0.0, success=s,
                         terminated=s) for i, s in enumerate(outcomes)]
    if varies is None:
        (run / "eval").mkdir()
        with open(run / "eval" / "eval.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["episode", "seed", "steps", "return", "env_return", "action_cost", "success", "terminated"])
            w.writerows([e.episode, e.seed, e.steps, e.ret, e.env_return, e.action_cost, e.success, e.terminated]
                        for e in eps)
    else:
        write_scenes_csv(run / "eval" / "scenes.csv", eps, [{"goal_x": 0.1 * i} if varies else {} for i in
                                                            range(len(eps))], varies)
    if task is not None:
        write_run_config(run, RunConfig(run_dir=str(run), task=task), {})


def test_report_shows_scenes_with_wilson_intervals_and_labels_one_scene(tmp_path):
    from khgrl.deploy.experiments.analysis import analyse

    exp = tmp_path / "exp"
    _experiment_run(exp / "pts-khgrl-seed0", [True] * 8 + [False] * 2, True)
    _experiment_run(exp / "pts-khgrl-seed1", [True] * 3 + [False] * 7, True)
    _experiment_run(exp / "pts-kgrl-seed0", [False] * 10, True)
    _experiment_run(exp / "pts-kgrl-seed1", [True] + [False] * 9, True)
    _experiment_run(exp / "box-khgrl-seed0", [True] * 4, False)  # scenes of a fixed-scene task
    _experiment_run(exp / "box-khgrl-seed1", [False] * 4, None, task=FIXED)  # eval.csv of a fixed-scene task
    _experiment_run(exp / "box-kgrl-seed0", [True] * 4, None, task=FIXED)
    text = analyse([exp], tmp_path / "report")
    lo, hi = wilson_interval(11, 20)
    assert f"| {11 / 20:.0%} ({lo:.0%}–{hi:.0%}; 11/20 scenes) (per seed: 8/10 = 80% (" in text
    lo, hi = wilson_interval(8, 10)
    assert f"8/10 = 80% ({lo:.0%}–{hi:.0%}), 3/10 = 30% (" in text
    assert "scenes: pooled over seeds, 95 % Wilson CI; per seed" in text
    assert "| one scene, not a rate: solved by 1 of 2 seeds (yes, no) |" in text
    assert "| one scene, not a rate: solved by 1 of 1 seeds (yes) |" in text
    comparison = text[text.index("KhGRL vs KGRL"):]
    assert "| box | 2/1 | " in comparison and comparison.count("one scene (not compared)") == 1  # not a rate
    assert "| eval success |" in comparison and "| +50% (p = " in comparison  # pts: 55% vs 5% (means over seeds)
    runs = {r["path"].rsplit("/", 1)[-1]: r for r in csv.DictReader(open(tmp_path / "report" / "per_run.csv"))}
    assert (runs["box-khgrl-seed1"]["eval_kind"], runs["pts-kgrl-seed1"]["eval_kind"]) == ("one scene", "scenes")
    assert runs["pts-khgrl-seed0"]["eval_successes"] == "8" and runs["pts-khgrl-seed0"]["eval_episodes"] == "10"


def test_scene_caption():
    from khgrl.deploy.tools.eval_scenes import scene_caption

    assert scene_caption(2, 8, {"goal_x": 0.8661, "goal_y": 0.385}) == "scene 2/8  goal_x=0.866  goal_y=0.385"
    assert scene_caption(1, 3, {}) == "scene 1/3"


def test_eval_adapts_the_kmp_as_the_run_did_unless_told(varying, tmp_path):
    """``--adapt/--no-adapt`` (default: the run's setting) reaches KGRLEnv: adapted, the KMP ends at each scene's goal
    (the task's via-point), so the untrained policy reaches goals that the demonstrations' KMP misses."""
    on = evaluate(varying, scenes=8, csv_path=tmp_path / "on.csv")
    off = evaluate(varying, scenes=8, csv_path=tmp_path / "off.csv", adapt=False)
    assert on.kmp == "KMP adapted to each scene's via-points" and off.kmp == "KMP not adapted (--no-adapt)"
    assert on.placements == off.placements  # the same scenes
    assert sum(e.success for e in on.episodes) > sum(e.success for e in off.episodes)
    run = _fake_run(tmp_path / "noadapt", VARYING, seed=4)
    cfg = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**cfg, "adapt": False}))
    default = evaluate(run, scenes=2, csv_path=tmp_path / "default.csv")
    assert default.kmp == off.kmp
