"""The ``khgrl`` command (deploy/cli.py)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from khgrl.common.tasks.demos import load_demos
from khgrl.deploy.cli import build_parser, main

VENV_KHGRL = Path(sys.executable).with_name("khgrl")


def _commands(parser: argparse.ArgumentParser, prefix=()):
    """Every command path of the parser: (), ("demos",), ("demos", "make"), ..."""
    yield prefix
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, prefix + (name,))


def _bench_commands():
    from khgrl.benchmarks.cli import build_parser as bench_parser

    return list(_commands(bench_parser(), ("bench",)))[1:]


ALL_COMMANDS = list(_commands(build_parser())) + _bench_commands()


def test_expected_commands_exist():
    for cmd in [("demos", "make"), ("kmp", "fit"), ("reference",), ("bench", "kmp"), ("bench", "runtime"),
                ("bench", "learner"), ("bench", "scale"), ("bench", "ingest"), ("bench", "secure"), ("bench", "flood"),
                ("up",), ("router",), ("learner",), ("actor",), ("human",), ("experiment",), ("report",), ("bench",)]:
        assert cmd in ALL_COMMANDS


def test_each_benchmark_is_declared_once_and_calls_its_function_with_its_flags():
    """khgrl bench's table: every benchmark's flags are keyword arguments of its run function."""
    import importlib
    import inspect

    from khgrl.benchmarks.cli import BENCHMARKS
    from khgrl.benchmarks.cli import build_parser as bench_parser

    subs = next(a for a in bench_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert set(subs) == set(BENCHMARKS)
    for name, bench in BENCHMARKS.items():
        params = inspect.signature(getattr(importlib.import_module(bench.module), bench.function)).parameters
        dests = {a.dest for a in subs[name]._actions if not isinstance(a, argparse._HelpAction)}
        assert dests <= set(params), (name, dests - set(params))


def test_process_commands_run_the_process_modules():
    """khgrl router/learner/actor/human run the process modules' main (the launcher's children's contract)."""
    from khgrl.deploy.cli import PROCESS_COMMANDS

    assert {k: v[:2] for k, v in PROCESS_COMMANDS.items()} == {
        "up": ("khgrl.deploy.run.launcher", "main"), "router": ("khgrl.deploy.run.router", "main"),
        "learner": ("khgrl.learner.main", "main"),
        "actor": ("khgrl.actor.main", "main"), "human": ("khgrl.human_bridge.main", "main"),
        "experiment": ("khgrl.deploy.experiments.experiment", "main"),
        "report": ("khgrl.deploy.experiments.report", "main"),
        "stop": ("khgrl.deploy.run.stop", "main"), "ready": ("khgrl.deploy.run.stop", "ready_main"),
        "view": ("khgrl.deploy.tools.view_cmd", "main"), "keys": ("khgrl.deploy.run.keys_cmd", "main"),
        "bench": ("khgrl.benchmarks.cli", "main"), "supervise": ("khgrl.deploy.run.supervise", "main")}


def _leaf_parsers(parser: argparse.ArgumentParser, prefix=()):
    """(command path, parser) of every parser without sub-commands below ``parser``."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix, parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from _leaf_parsers(sub, prefix + (name,))


def _parsers_of(command: str):
    """(command path, parser) of every leaf parser of ``command`` ("khgrl": the khgrl parser's own commands;
    a process command: its module's build_parser)."""
    import importlib

    from khgrl.deploy.cli import PROCESS_COMMANDS

    if command == "khgrl":
        return [(c, p) for c, p in _leaf_parsers(build_parser()) if c and c[0] not in PROCESS_COMMANDS]

    mod = importlib.import_module(PROCESS_COMMANDS[command][0])
    assert hasattr(mod, "build_parser"), f"{mod.__name__} has no build_parser()"
    return list(_leaf_parsers(mod.build_parser(), (command,)))


@pytest.mark.parametrize("command", ["khgrl", "up", "router", "learner", "actor", "human", "experiment", "bench"])
def test_help_shows_every_default(command):
    """--help states each option's default (a value, 'none', 'off', ...)."""
    missing = [(" ".join(cmd), a.option_strings[-1]) for cmd, parser in _parsers_of(command)
               for a in parser._actions
               if a.option_strings and a.help != argparse.SUPPRESS and not isinstance(a, argparse._HelpAction)
               and not a.required and "default" not in (a.help or "").lower()]
    assert not missing, f"options whose --help shows no default: {missing}"


def test_up_help_lists_every_run_setting(capsys):
    """khgrl up takes every RunConfig field as a flag, plus --config, --resume, --overwrite, --progress."""
    from khgrl.common.config.settings import _flag_fields

    with pytest.raises(SystemExit):
        main(["up", "--help"])
    out = capsys.readouterr().out
    for path, _, _ in _flag_fields():
        assert "--" + path[-1].replace("_", "-") in out
    for flag in ("--config", "--resume", "--overwrite", "--no-progress"):
        assert flag in out


@pytest.mark.parametrize("command", ["khgrl", "up", "router", "learner", "actor", "human", "experiment", "bench"])
def test_no_option_states_its_default_twice(command):
    """Newcomer defect 8: khgrl up --help said "(default: none) (default: none)". Every option of every command
    states its default once."""
    twice = [(" ".join(cmd), a.option_strings[-1], text) for cmd, parser in _parsers_of(command)
             for a in parser._actions if a.option_strings and a.help and a.help != argparse.SUPPRESS
             for text in [parser._get_formatter()._expand_help(a)] if text.lower().count("default") > 1]
    assert not twice, f"options whose --help states the default twice: {twice}"


def test_up_help_of_the_installed_command_states_each_default_once():
    exe = VENV_KHGRL if VENV_KHGRL.exists() else None
    if exe is None:
        pytest.skip("khgrl console script not installed next to this interpreter")
    res = subprocess.run([str(exe), "up", "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    text = " ".join(res.stdout.split())
    assert "(default: none) (default: none)" not in text
    assert "--run RUN run id, the key prefix khgrl/<run>/ (default: derived from the run directory)" in text


@pytest.mark.parametrize("cmd", ALL_COMMANDS, ids=lambda c: " ".join(c) or "khgrl")
def test_help_exits_zero(cmd, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*cmd, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: khgrl")


def test_console_script_help():
    exe = VENV_KHGRL if VENV_KHGRL.exists() else None
    if exe is None:
        pytest.skip("khgrl console script not installed next to this interpreter")
    res = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "demos" in res.stdout and "kmp" in res.stdout and "reference" in res.stdout


def test_no_command_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2
    assert "usage" in capsys.readouterr().err


def test_demos_make_csv(tmp_path):
    path = tmp_path / "d.csv"
    assert main(["demos", "make", "--n-demos", "3", "--n-steps", "20", "--out", str(path)]) == 0
    assert path.read_text().splitlines()[0] == "demo,step,y0,y1"
    assert load_demos(path).shape == (3, 20, 2)


def test_demos_make_then_kmp_fit(tmp_path, capsys):
    demos_path = tmp_path / "demos.npz"
    assert main(["demos", "make", "--scenario", "low_cov", "--n-demos", "4", "--n-steps", "120", "--seed", "3",
                 "--out", str(demos_path)]) == 0
    assert "wrote 4 demonstrations x 120 steps x 2 outputs" in capsys.readouterr().out
    demos = load_demos(demos_path)
    assert demos.shape == (4, 120, 2)

    png = tmp_path / "fig" / "kmp.png"
    png.parent.mkdir()
    rc = main(["kmp", "fit", str(demos_path), "--out", str(png), "--components", "4", "--box", "0.02", "0.98",
               "--scenario", "low_cov"])
    assert rc == 0
    out = capsys.readouterr().out
    assert str(png) in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 1000
    summary = json.loads(png.with_suffix(".json").read_text())
    assert summary["shape"] == [4, 120, 2]
    assert summary["box"] == [0.02, 0.98]
    assert summary["config"]["n_components"] == 4
    assert 0 < summary["projector_min"] <= summary["projector_max"]
    assert np.isfinite(summary["mean_minus_gmr_max_abs"])


def test_demos_make_is_seeded(tmp_path):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    assert main(["demos", "make", "--out", str(a), "--seed", "7"]) == 0
    assert main(["demos", "make", "--out", str(b), "--seed", "7"]) == 0
    np.testing.assert_array_equal(load_demos(a), load_demos(b))
    assert load_demos(a).shape == (9, 400, 2)


def test_missing_demo_file_exit_2(tmp_path, capsys):
    missing = tmp_path / "nope.npz"
    rc = main(["kmp", "fit", str(missing), "--out", str(tmp_path / "k.png")])
    assert rc == 2
    captured = capsys.readouterr()
    assert "khgrl: error:" in captured.err and "no such file" in captured.err and str(missing) in captured.err
    assert not (tmp_path / "k.png").exists()


def test_bad_demo_file_exit_2(tmp_path, capsys):
    bad = tmp_path / "ragged.csv"
    bad.write_text("demo,step,y0\n0,0,1\n0,1,2\n1,0,1\n")
    assert main(["kmp", "fit", str(bad), "--out", str(tmp_path / "k.png")]) == 2
    assert "ragged" in capsys.readouterr().err


def test_demos_make_bad_extension_exit_2(tmp_path, capsys):
    assert main(["demos", "make", "--out", str(tmp_path / "d.txt")]) == 2
    assert "unknown demonstration format" in capsys.readouterr().err


def test_bad_choice_is_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demos", "make", "--scenario", "nope", "--out", "x.npz"])
    assert exc.value.code == 2


def test_report_on_committed_reference_runs(tmp_path):
    from pathlib import Path

    from khgrl.deploy.cli import main

    docs = Path(__file__).resolve().parents[2] / "docs" / "reference_runs"
    out = tmp_path / "rep.png"
    assert main(["report", str(docs / "low_cov-kgrl-seed0"), str(docs / "low_cov-khgrl-seed0"), "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
    table = out.with_suffix(".md").read_text()
    assert "| low_cov-kgrl-seed0 | 0/60 |" in table and "| low_cov-khgrl-seed0 | 51/60 |" in table


def test_report_missing_run_dir(tmp_path, capsys):
    from khgrl.deploy.cli import main

    assert main(["report", str(tmp_path / "nope")]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert main(["report", str(tmp_path)]) == 2  # a directory with neither runs nor episode results
    assert "no episodes.csv" in capsys.readouterr().err


def test_reference_defaults_and_flags_come_from_the_run_settings():
    """One source of defaults: ReferenceConfig's are RunConfig's, and khgrl reference's flags are RunConfig's
    (with the TQC settings, which the reference did not take before)."""
    from dataclasses import fields

    from khgrl.common.config.settings import RunConfig, TQCSettings, resolve
    from khgrl.learner.baseline import ReferenceConfig

    ref, run = ReferenceConfig(), RunConfig()
    assert all(getattr(ref, f.name) == getattr(run, f.name) for f in fields(ref))
    args = build_parser().parse_args(["reference", "--scenario", "low_cov", "--episodes", "3", "--learning-rate",
                                      "0.01", "--human-episodes", "2"])
    assert ReferenceConfig.from_run(resolve(args=args)) == ReferenceConfig(
        scenario="low_cov", episodes=3, human_episodes=(2,), tqc=TQCSettings(learning_rate=0.01))
    assert ReferenceConfig.from_run(resolve(args=build_parser().parse_args(["reference"]))) == ref


def test_bench_runs_through_khgrl_by_module_name(capsys):
    """khgrl bench is dispatched by name to khgrl.benchmarks.cli (deploy does not import benchmarks); a bad
    setting is one line and exit 2."""
    assert main(["bench", "kmp", "--repeats", "5"]) == 2
    assert "khgrl bench: error: repeats must be >= 20" in capsys.readouterr().err


@pytest.mark.parametrize("bench", ["ingest", "secure"])
def test_bench_senders_must_be_at_least_one(bench, capsys):
    """``khgrl bench ingest --senders 0`` used to end in a ZeroDivisionError after starting a learner."""
    from khgrl.benchmarks.cli import build_parser as bench_parser

    with pytest.raises(SystemExit) as exc:
        bench_parser().parse_args([bench, "--senders", "0"])
    assert exc.value.code == 2 and "--senders: 0 is not >= 1" in capsys.readouterr().err
