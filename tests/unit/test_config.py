"""common/config/settings.py: the one source of settings -- defaults < file < flags, files that read back to the same
configuration, and clear errors for bad settings."""

from __future__ import annotations

import argparse
import json
import re

import pytest
from khgrl.common.config.process import add_process_flags, resolve_process
from khgrl.common.config.settings import (
    PAPER_EPISODES,
    RunConfig,
    StreamSettings,
    TQCSettings,
    add_config_flags,
    read_run_file,
    resolve,
    to_toml,
    write_run_config,
)


def _parser(process: bool = False) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    if process:
        add_process_flags(p)
    else:
        add_config_flags(p)
    return p


def test_defaults_are_the_papers_settings():
    cfg = resolve()
    assert cfg.tqc == TQCSettings() and cfg.tqc.train_freq == 8 and cfg.tqc.net_arch == (256, 256)
    assert cfg.human_episodes == PAPER_EPISODES and cfg.stream.max_lead == cfg.tqc.train_freq
    kw = cfg.tqc.sb3_kwargs(seed=3)
    assert kw["policy_kwargs"] == {"net_arch": [256, 256]} and kw["seed"] == 3 and kw["learning_starts"] == 100


def test_flags_override_the_file_which_overrides_defaults(tmp_path):
    f = tmp_path / "run.toml"
    f.write_text('episodes = 7\nseed = 4\n[stream]\nmax_lead = 32\n[tqc]\nlearning_starts = 50\n')
    args = _parser().parse_args(["--seed", "9", "--batch", "16", "--no-tensorboard"])
    cfg = resolve(f, args)
    assert (cfg.episodes, cfg.seed, cfg.stream.max_lead, cfg.stream.batch) == (7, 9, 32, 16)
    assert cfg.tqc.learning_starts == 50 and cfg.tensorboard is False
    assert cfg.method == "khgrl"  # untouched: the default


def test_toml_and_run_files_read_back_to_the_same_configuration(tmp_path):
    args = _parser().parse_args(["--scenario", "low_cov", "--human-episodes", "2", "3", "--net-arch", "64", "64",
                                 "--max-lead", "16", "--rate", "50"])
    cfg = resolve(None, args)
    (tmp_path / "c.toml").write_text(to_toml(cfg))
    assert resolve(tmp_path / "c.toml") == cfg
    write_run_config(tmp_path / "run", cfg, {"run": "r1", "endpoint": "tcp/127.0.0.1:9"})
    again, runtime = read_run_file(tmp_path / "run" / "config.json")
    assert again == cfg and runtime == {"run": "r1", "endpoint": "tcp/127.0.0.1:9"}
    assert resolve(tmp_path / "run" / "config.toml") == cfg


@pytest.mark.parametrize("text, words", [
    ("bogus = 1\n", "unknown setting"),
    ("[tqc]\nbogus = 1\n", "config.tqc: unknown"),
    ('episodes = "ten"\n', "config.episodes: expected an integer"),
    ("episodes = true\n", "expected an integer"),
    ("tensorboard = 1\n", "expected true/false"),
    ('method = "mars"\n', "not one of khgrl, kgrl"),
    ('human = "replay"\n', "needs replay"),
    ("episodes = 0\n", "episodes and actors must be >= 1"),
    ("[stream]\nmax_lead = 4\n", "max_lead must be >= the learner's train frequency"),
    ('run = "a/b"\n', "run id"),
    ("human_episodes = [0]\n", "counted from 1"),
    ("actor_rt_priority = 10\n", "needs rate > 0"),
    ("stream = 3\n", "expected a table"),
    ("episodes = [\n", "not valid TOML"),
])
def test_a_bad_setting_is_refused_by_name(tmp_path, text, words):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ValueError, match=words):
        resolve(f)


def test_a_missing_config_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        resolve(tmp_path / "nope.toml")


def test_every_setting_is_a_flag_whose_help_shows_its_default():
    text = _parser().format_help()
    text = text[text.index("run settings"):]  # the options, not the usage line
    for flag, default in (("--max-lead", "8"), ("--learning-starts", "100"), ("--net-arch", "256 256"),
                          ("--human-episodes", " ".join(map(str, PAPER_EPISODES))), ("--connect-timeout", "15.0"),
                          ("--checkpoint-every", "0"), ("--tensorboard", "True")):
        assert flag in text
        after = " ".join(text[text.index(flag):].split())
        shown = re.search(r"\(default: ([^)]*)\)", after)
        assert shown is not None and shown.group(1) == default, flag


def test_a_process_reads_the_run_file_and_its_flags_win(tmp_path):
    cfg = resolve(overrides={"episodes": 5, "stream": {"max_lead": 16}})
    path = write_run_config(tmp_path, cfg, {"run": "myrun", "endpoint": "tcp/127.0.0.1:4000"})
    pc = resolve_process(_parser(True).parse_args(["--config", str(path), "--max-lead", "24"]))
    assert (pc.run, pc.endpoint, pc.cfg.episodes, pc.cfg.stream.max_lead) == ("myrun", "tcp/127.0.0.1:4000", 5, 24)
    pc = resolve_process(_parser(True).parse_args(["--config", str(path), "--run", "other", "--connect",
                                                   "tcp/10.0.0.1:7447"]))
    assert (pc.run, pc.endpoint) == ("other", "tcp/10.0.0.1:7447")
    with pytest.raises(ValueError, match="no run id"):
        resolve_process(_parser(True).parse_args([]))


def test_actor_seeds_follow_the_actor_index():
    cfg = RunConfig(seed=10, actors=3)
    assert [cfg.actor_seed(a) for a in cfg.actor_ids()] == [10, 11, 12]
    # an actor started by hand beyond ``actors`` still gets its own seed, and so does an id of another form: two
    # actors never collect the same transitions (the learner would refuse the second's as replays)
    assert RunConfig(seed=10).actor_seed("a1") == 11
    assert len({cfg.actor_seed(a) for a in ("robot-left", "robot-right", "a0", "a1", "a2")}) == 5
    assert cfg.actor_seed("robot-left") == RunConfig(seed=10).actor_seed("robot-left")  # (the same on every run)


def test_settings_are_frozen_and_json_serialisable():
    cfg = RunConfig()
    with pytest.raises(Exception):
        cfg.seed = 3  # type: ignore[misc]
    assert json.loads(json.dumps(cfg.to_dict()))["stream"] == json.loads(json.dumps(
        StreamSettings().__dict__))


def test_learner_device_auto_is_cpu_without_a_gpu_and_cuda_is_refused_clearly(monkeypatch):
    import torch
    from khgrl.common.config.settings import TQCSettings
    from khgrl.learner.trainer import build_model, torch_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert TQCSettings().device == "auto" and torch_device("auto") == "cpu" and torch_device("cpu") == "cpu"
    assert build_model(TQCSettings(), 0).device.type == "cpu"
    with pytest.raises(ValueError, match="no CUDA device"):
        torch_device("cuda")
    with pytest.raises(ValueError, match="no CUDA device"):
        build_model(TQCSettings(device="cuda"), 0)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert torch_device("auto") == "cuda" and torch_device("cpu") == "cpu"


# ------------------------------------------------------------------------------------ roles: per-process flags
def _flags(parser: argparse.ArgumentParser) -> set[str]:
    """The setting names of a parser's run-setting flags (dest cfg__...)."""
    return {a.dest.split("__")[-1] for a in parser._actions if a.dest.startswith("cfg__")}


def _process_parsers() -> dict[str, list[argparse.ArgumentParser]]:
    """Each command's real parser(s): khgrl up, learner, actor, every khgrl human client, reference."""
    from khgrl.actor.main import build_parser as actor
    from khgrl.deploy.cli import build_parser as khgrl
    from khgrl.deploy.run.launcher import build_parser as up
    from khgrl.human_bridge.main import build_parser as human
    from khgrl.learner.main import build_parser as learner

    def subs(parser):
        return {name: p for a in parser._actions if isinstance(a, argparse._SubParsersAction)
                for name, p in a.choices.items()}

    return {"up": [up()], "learner": [learner()], "actor": [actor()], "human": list(subs(human()).values()),
            "reference": [subs(khgrl())["reference"]]}


def test_each_commands_flags_are_the_settings_whose_roles_name_it():
    from dataclasses import fields as dc_fields

    from khgrl.common.config.hilserl import HilSerlSettings
    from khgrl.common.config.settings import ROLES, SafetySettings, role_fields

    every = [f for cls in (RunConfig, TQCSettings, StreamSettings, SafetySettings, HilSerlSettings)
             for f in dc_fields(cls) if cls is not RunConfig or f.name not in ("tqc", "stream", "safety", "hilserl")]
    for f in every:  # every setting says which commands take it, and khgrl up takes it
        assert "up" in f.metadata["roles"] and f.metadata["roles"] <= set(ROLES), f.name
    parsers = _process_parsers()
    assert set(parsers) == set(ROLES)
    for role, ps in parsers.items():
        for p in ps:
            assert _flags(p) == set(role_fields(role)), (role, p.prog)
    assert _flags(parsers["up"][0]) == {f.name for f in every}  # every field is a flag (of up at least)
    # the processes take what they use: the learner its TQC settings, the actor its stream settings
    assert {"learning_rate", "batch_size", "checkpoint_every", "device"} <= set(role_fields("learner"))
    assert {"max_lead", "window", "rate", "method", "rate_limit", "human_silence_s"} <= set(role_fields("actor"))
    assert "run_dir" not in role_fields("reference") and "learning_rate" in role_fields("reference")


def test_a_new_setting_must_name_its_roles():
    from khgrl.common.config import settings

    with pytest.raises(TypeError, match="roles"):
        settings._opt(1, "a setting without roles")  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="unknown role"):
        settings._opt(1, "a setting of a command that does not exist", roles=("robot",))


def test_every_human_client_is_a_choice_of_up_and_replay_runs_from_the_config(tmp_path):
    """HUMANS (khgrl up --human) lists every client of khgrl human; --human replay takes --replay FILE, which the
    replay client reads from the run's config.json (khgrl up starts it with --config only)."""
    from khgrl.common.config.settings import HUMANS
    from khgrl.deploy.run.launcher import build_parser as up
    from khgrl.human_bridge.main import CLIENTS
    from khgrl.human_bridge.main import build_parser as human

    assert set(HUMANS) == set(CLIENTS) | {"none"}
    with pytest.raises(ValueError, match="needs replay"):
        resolve(args=up().parse_args(["--human", "replay"]))
    cfg = resolve(args=up().parse_args(["--human", "replay", "--replay", "old/actor-a0/corrections.csv"]))
    path = write_run_config(tmp_path, cfg, {"run": "r", "endpoint": "tcp/127.0.0.1:9"})
    args = human().parse_args(["replay", "--config", str(path), "--id", "replay"])
    assert args.file is None and resolve_process(args).cfg.replay == "old/actor-a0/corrections.csv"
    assert "replay" in _flags(_process_parsers()["human"][0])


def test_the_passage_scenario_is_checked_where_the_task_is_built():
    """The shared settings do not know the passage world's scenarios; its task module refuses a wrong one."""
    from khgrl.common.tasks.api import TaskError, load_task

    cfg = resolve(overrides={"scenario": "mars"})
    with pytest.raises(TaskError, match="unknown scenario 'mars'.*high_cov"):
        load_task(cfg.task_spec)
    import ast
    import pathlib

    import khgrl.common.config as config_package

    for path in pathlib.Path(config_package.__file__).parent.glob("*.py"):  # no import of a task
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
                assert not any("common.tasks" in n for n in names), (path.name, names)
