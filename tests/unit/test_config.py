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
    ('scenario = "mars"\n', "not one of high_cov, low_cov"),
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
                          ("--checkpoint-every", "2000"), ("--tensorboard", "True")):
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
