"""khgrl experiment: config, run plan, resumability (a finished run is kept, an interrupted one redone or resumed)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest
from khgrl.deploy.experiments.experiment import ExperimentConfig, RunSpec, load_config, plan_runs, run_argv, run_is_done

from helpers import REPO, SMALL_UP, wait_for


def test_config_file_then_overrides(tmp_path):
    f = tmp_path / "exp.toml"
    f.write_text('out = "x"\nseeds = [3, 4]\nepisodes = 7\nmethods = ["kgrl"]\n')
    cfg = load_config(f, {"episodes": 9, "jobs": None})
    assert (cfg.out, cfg.seeds, cfg.episodes, cfg.methods, cfg.jobs) == ("x", [3, 4], 9, ["kgrl"], 1)
    j = tmp_path / "exp.json"
    j.write_text(json.dumps({"scenarios": ["low_cov"], "system": "reference"}))
    assert load_config(j, {}).system == "reference"


@pytest.mark.parametrize("text,match", [
    ('seedz = [1]', "unknown keys"),
    ('scenarios = ["mars"]', "unknown scenario"),
    ('seeds = [1, 1]', "distinct"),
    ('episodes = 0', ">= 1"),
    ('system = "cloud"', "system"),
    ('tasks = ["fetch"]', "expected"),
    ('tasks = ["a.b:c", "a_b:c"]', "share a run directory"),
    ('tasks = ["fetch:moved"]\nsystem = "reference"', "scenarios only"),
    ('up_args = ["--seed", "3"]', "the grid sets these itself"),
    ('up_args = ["--episodes=3"]', "the grid sets these itself"),
    ('up_args = ["--see", "3"]', "the grid sets these itself"),  # (an abbreviation of --seed)
    ('up_args = ["--no-such-flag"]', "not flags khgrl up takes"),
    ('up_args = "--net-arch 64"', "list of strings"),
    ('up_args = ["--net-arch", "64"]\nsystem = "reference"', "distributed"),
])
def test_bad_configs_are_refused(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text + "\n")
    with pytest.raises(ValueError, match=match):
        load_config(f, {})


def test_plan_is_seed_major_and_commands_match_the_method(tmp_path):
    cfg = ExperimentConfig(seeds=[0, 1], scenarios=["high_cov"], human_episodes=[2, 3])
    specs = plan_runs(cfg)
    assert [s.name for s in specs] == ["high_cov-khgrl-seed0", "high_cov-kgrl-seed0", "high_cov-khgrl-seed1",
                                       "high_cov-kgrl-seed1"]
    kh = run_argv(specs[0], cfg, tmp_path / "r")
    assert kh[kh.index("--human") + 1] == "scripted" and kh[kh.index("--human-episodes") + 1:][:2] == ["2", "3"]
    kg = run_argv(specs[1], cfg, tmp_path / "r")
    assert kg[kg.index("--human") + 1] == "none" and "up" in kg
    ref = run_argv(RunSpec("low_cov", "kgrl", 2), ExperimentConfig(system="reference"), tmp_path / "r")
    assert "reference" in ref and ref[ref.index("--seed") + 1] == "2"


def test_run_argv_is_a_valid_khgrl_up_command(tmp_path):
    """The command of a distributed run resolves (khgrl up's parser and common.config.settings) to the planned run."""
    from khgrl.common.config.settings import resolve
    from khgrl.deploy.cli import build_parser as cli_parser
    from khgrl.deploy.run.launcher import build_parser

    cfg = ExperimentConfig(seeds=[3], scenarios=["low_cov"], episodes=7, human_episodes=[2, 3], timeout=99,
                           up_args=["--net-arch", "64", "64", "--batch-size", "32"]).validate()
    for spec in plan_runs(cfg):
        argv = run_argv(spec, cfg, tmp_path / spec.name)
        args = build_parser().parse_args(argv[argv.index("up") + 1:])
        run = resolve(args.config, args)
        assert (run.scenario, run.method, run.seed, run.episodes, run.timeout) == ("low_cov", spec.method, 3, 7, 99.0)
        assert run.run_dir == str(tmp_path / spec.name) and run.stream.max_lead == 8 and not args.progress
        assert (run.tqc.net_arch, run.tqc.batch_size) == ((64, 64), 32)  # up_args
        if spec.method == "khgrl":
            assert (run.human, run.human_episodes) == ("scripted", (2, 3))
        else:
            assert run.human == "none"
    ref = run_argv(RunSpec("low_cov", "kgrl", 2), ExperimentConfig(system="reference", episodes=4), tmp_path / "r")
    args = cli_parser().parse_args(ref[ref.index("reference"):])
    run = resolve(args=args)  # khgrl reference's flags are the run settings' (role "reference")
    assert (run.scenario, run.method, run.seed, run.episodes, args.quiet) == ("low_cov", "kgrl", 2, 4, True)


def test_tasks_replace_scenarios_in_the_plan_and_the_commands(tmp_path):
    """``tasks``: one run per task, method and seed, named after the task; each command is ``khgrl up --task``."""
    from khgrl.common.config.settings import resolve
    from khgrl.deploy.run.launcher import build_parser

    cfg = ExperimentConfig(seeds=[1], tasks=["fetch:control", "khgrl.deploy.examples.own_task:make_task"], episodes=3,
                           human_episodes=[2])
    specs = plan_runs(cfg)
    assert [s.name for s in specs] == ["fetch_control-khgrl-seed1", "fetch_control-kgrl-seed1",
                                       "khgrl_deploy_examples_own_task_make_task-khgrl-seed1",
                                       "khgrl_deploy_examples_own_task_make_task-kgrl-seed1"]
    for spec in specs:
        argv = run_argv(spec, cfg, tmp_path / spec.name)
        assert "--scenario" not in argv
        run = resolve(None, build_parser().parse_args(argv[argv.index("up") + 1:]))
        assert (run.task_spec, run.method, run.seed, run.episodes) == (spec.task, spec.method, 1, 3)


def test_run_is_done_only_for_a_complete_clean_run(tmp_path):
    cfg = ExperimentConfig(episodes=3)
    d = tmp_path / "run"
    d.mkdir()
    assert not run_is_done(d, cfg)
    good = {"failed": [], "interrupted": False, "exit_codes": {"router": 0, "learner": 0, "a0": 0},
            "a0": {"episodes": 3, "unconfirmed_transitions": 0}}
    for bad in ({"failed": ["a0"]}, {"interrupted": True}, {"exit_codes": {"a0": 1}}, {"a0": {"episodes": 2}},
                {"a0": {"episodes": 3, "unconfirmed_transitions": 5}}):
        (d / "summary.json").write_text(json.dumps({**good, **bad}))
        assert not run_is_done(d, cfg), bad
    (d / "summary.json").write_text(json.dumps(good))
    assert run_is_done(d, cfg)
    (d / "summary.json").write_text("{truncated")
    assert not run_is_done(d, cfg)
    early = {**good, "a0": {"episodes": 2, "unconfirmed_transitions": 0, "converged": True}}  # --until-success
    (d / "summary.json").write_text(json.dumps(early))
    assert run_is_done(d, cfg)


def test_until_success_goes_to_every_run_and_is_checked(tmp_path):
    cfg = load_config(None, {"tasks": ["fetch:moved"], "methods": ["khgrl"], "until_success": 0.8})
    argv = run_argv(plan_runs(cfg)[0], cfg, tmp_path / "r")
    i = argv.index("--until-success")
    assert argv[i:i + 4] == ["--until-success", "0.8", "--success-window", "20"]
    assert "--until-success" not in run_argv(plan_runs(load_config(None, {}))[0], load_config(None, {}), tmp_path)
    for bad in ({"until_success": 1.5}, {"success_window": 0}, {"until_success": 0.8, "system": "reference"}):
        with pytest.raises(ValueError):
            load_config(None, bad)


def _argv(out, *extra):
    return [sys.executable, "-m", "khgrl.deploy.cli", "experiment", "--out", str(out), "--scenarios", "low_cov",
            "--methods", "kgrl", "--seeds", "0", "--episodes", "3", "--no-progress", "--timeout", "240", SMALL_UP,
            *extra]


def _experiment(out, *extra, timeout=300):
    return subprocess.run(_argv(out, *extra), cwd=REPO, capture_output=True, text=True, timeout=timeout)


def _rows(run):
    return (run / "actor-a0" / "episodes.csv").read_text().splitlines()[1:]


@pytest.mark.integration
@pytest.mark.timeout(600)
def test_experiment_runs_resumes_and_redoes_an_interrupted_run(tmp_path):
    """Ctrl-C after the first episode, then ``--resume-interrupted`` goes on from the checkpoint (the episodes of
    the first part kept, one log); a finished run is not redone; without the flag an interrupted run is wiped."""
    out, name = tmp_path / "exp", "low_cov-kgrl-seed0"
    run = out / name
    first = subprocess.Popen(_argv(out), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wait_for(lambda: "[a0] episode 1:" in _read(run / "experiment.log"), 240, "the first episode")
    first.send_signal(signal.SIGINT)
    assert first.wait(120) == 130, first.stdout.read()
    doc = json.loads((out / "experiment.json").read_text())
    assert doc["runs"][name]["status"] == "interrupted"
    kept = _rows(run)
    assert 1 <= len(kept) < 3, "the run was to be cut short"
    resumed = _experiment(out, "--resume-interrupted")
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    rows = _rows(run)
    assert len(rows) == 3 and rows[:len(kept)] == kept and [r.split(",")[0] for r in rows] == ["1", "2", "3"]
    doc = json.loads((out / "experiment.json").read_text())
    assert doc["runs"][name]["status"] == "done" and doc["runs"][name]["parts"] == 2
    assert "--resume" in doc["runs"][name]["argv"] and "[a0] episode 1:" in _read(run / "experiment.log")
    stamp = (run / "summary.json").stat().st_mtime_ns
    again = _experiment(out, "--resume-interrupted")  # finished: not redone
    assert again.returncode == 0 and "finished before, not redone" in again.stdout
    assert (run / "summary.json").stat().st_mtime_ns == stamp
    # interrupted (no summary, leftovers), without the flag: wiped and started again from scratch (here cut by a
    # 1 s timeout: the wipe is what is checked, the run itself was checked above)
    (run / "summary.json").unlink()
    (run / "leftover.txt").write_text("half a run")
    third = _experiment(out, "--timeout", "1")
    assert third.returncode == 1, third.stdout + third.stderr
    assert "no run finished" in third.stdout and "analyse with" not in third.stdout  # (every run failed)
    episodes = run / "actor-a0" / "episodes.csv"  # (the episodes of before gone with the rest)
    assert not (run / "leftover.txt").exists() and (not episodes.is_file() or len(_rows(run)) < 3)
    entry = json.loads((out / "experiment.json").read_text())["runs"][name]
    assert entry["parts"] == 1 and entry["status"] == "failed" and "--resume" not in entry["argv"]


def _read(path):
    try:
        return path.read_text()
    except OSError:
        return ""


def test_experiment_cli_reports_bad_config(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("episodes = 'many'\n")
    proc = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "experiment", str(f), "--dry-run"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "khgrl experiment: error" in proc.stderr
    grid = [sys.executable, "-m", "khgrl.deploy.cli", "experiment", "--out", str(tmp_path / "o"), "--scenarios",
            "low_cov", "--methods", "kgrl", "--seeds", "0", "--dry-run"]
    proc = subprocess.run([*grid, "--up-args=--net-arch 64 64"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.rstrip().endswith("--net-arch 64 64"), proc.stdout + proc.stderr
    proc = subprocess.run([*grid, "--up-args=--seed 4"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "the grid sets these itself" in proc.stderr, proc.stderr
