"""The grid of ``khgrl experiment``: its settings (:class:`ExperimentConfig`, a config file's keys), the runs it
plans (seed-major), the command of one run (the same ``khgrl up`` a user types) and whether a run directory
holds a finished run. Nothing here runs anything: :mod:`khgrl.deploy.experiments.experiment` does.
"""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from khgrl.common.config.settings import HUMAN_METHODS, PAPER_EPISODES, REFERENCE_METHODS, TQCSettings, read_table
from khgrl.common.tasks.passage.scenarios import SCENARIOS
from khgrl.deploy.experiments.experiment_ray import DEFAULT_CPUS, check_ray_settings
from khgrl.deploy.experiments.run_results import METHOD_LABEL

__all__ = ["SYSTEMS", "GRID_DESTS", "ExperimentConfig", "check_up_args", "RunSpec", "task_label", "load_config",
           "plan_runs", "run_is_done", "run_argv"]

SYSTEMS = ("distributed", "reference")


@dataclass
class ExperimentConfig:
    """The grid and how each run is made (the keys of a config file)."""

    out: str = "runs/experiment"
    scenarios: list[str] = field(default_factory=lambda: list(SCENARIOS))
    tasks: list[str] = field(default_factory=list)  # task specs (khgrl up --task); if given, instead of scenarios
    methods: list[str] = field(default_factory=lambda: list(REFERENCE_METHODS))
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4])
    episodes: int = 60
    human_episodes: list[int] = field(default_factory=lambda: list(PAPER_EPISODES))
    system: str = "distributed"  # "distributed": khgrl up; "reference": single-process SB3 (khgrl reference)
    jobs: int = 1  # runs at a time
    max_lead: int = 8  # khgrl up --max-lead (8: lock-step with the learner, as the single-process reference)
    timeout: float = 0.0  # seconds per run (0: none)
    until_success: float = 0.0  # khgrl up --until-success: a run ends once it holds this autonomous success rate
    success_window: int = 20  # ... over this many autonomous episodes
    resume_interrupted: bool = False  # continue an interrupted run from its checkpoint (khgrl up --resume)
    ray: str = ""  # a Ray cluster's address (or "auto", "local"): each run a Ray task there (experiment_ray.py)
    ray_cpus: float = DEFAULT_CPUS  # per run, with ray
    ray_gpus: float = 0.0  # per run, with ray (> 0: the learner runs with --device cuda)
    up_args: list[str] = field(default_factory=list)  # more khgrl up flags for every run: ["--net-arch", "64", "64"]

    def validate(self) -> "ExperimentConfig":
        bad = [s for s in self.scenarios if s not in SCENARIOS] + [m for m in self.methods if m not in METHOD_LABEL]
        if bad:
            raise ValueError(f"unknown scenario/method {bad}; choose from {tuple(SCENARIOS)} and "
                             f"{tuple(METHOD_LABEL)}")
        if self.system == "reference" and any(m not in REFERENCE_METHODS for m in self.methods):
            raise ValueError(f"the single-process reference runs the methods {REFERENCE_METHODS} only")
        bad_tasks = [t for t in self.tasks if not isinstance(t, str) or ":" not in t]
        if bad_tasks:
            raise ValueError(f"tasks {bad_tasks}: expected 'passage:SCENARIO', 'fetch:SCENARIO' or "
                             "'package.module:callable'")
        if not 0.0 <= self.until_success <= 1.0 or self.success_window < 1:
            raise ValueError("until_success must be in [0, 1] and success_window >= 1")
        if self.until_success and self.system == "reference":
            raise ValueError("the single-process reference runs every episode (no until_success)")
        if self.tasks and self.system == "reference":
            raise ValueError("the single-process reference runs the passage world's scenarios only, not tasks")
        if len({task_label(t) for t in self.tasks}) != len(self.tasks):
            raise ValueError(f"tasks {self.tasks}: two of them would share a run directory name")
        if self.system not in SYSTEMS:
            raise ValueError(f"system must be one of {SYSTEMS}, not {self.system!r}")
        if not self.seeds or any(int(s) < 0 for s in self.seeds) or len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds must be distinct non-negative integers, got {self.seeds}")
        if self.episodes < 1 or self.jobs < 1:
            raise ValueError("episodes and jobs must be >= 1")
        if self.max_lead < TQCSettings().train_freq:
            raise ValueError(f"max_lead must be >= the learner's train frequency ({TQCSettings().train_freq})")
        if any(e < 1 for e in self.human_episodes):
            raise ValueError("human_episodes are 1-based episode numbers")
        check_ray_settings(self.ray, self.ray_cpus, self.ray_gpus, self.system)
        check_up_args(self.up_args, self.system)
        return self


# what the grid sets in each run itself (run_argv), by khgrl up's argument names: up_args may not set them
GRID_DESTS = frozenset({"task", "scenario", "method", "seed", "episodes", "run_dir", "max_lead", "progress", "adapt",
                        "sampling", "takeover", "recipe", "human", "human_episodes", "timeout", "until_success",
                        "success_window", "resume", "overwrite", "config"})


def check_up_args(up_args: list[str], system: str) -> None:
    """``up_args`` are ``khgrl up`` flags that its parser takes, none of them one the grid sets (ValueError if not;
    read by the parser itself, so an abbreviation or ``--flag=value`` counts as the flag).

    :param up_args: the flags
    :param system: the grid's system (up_args need ``distributed``)
    """
    if not up_args:
        return
    if not isinstance(up_args, list) or not all(isinstance(a, str) for a in up_args):
        raise ValueError(f"up_args must be a list of strings, got {up_args!r}")
    if system != "distributed":
        raise ValueError("up_args are khgrl up's flags: they need system = \"distributed\"")
    from khgrl.deploy.run.launcher import build_parser  # (khgrl up's own parser; imported only when needed)

    parser = build_parser()
    try:
        given = vars(parser.parse_args(up_args))
    except SystemExit:  # (argparse has printed why)
        raise ValueError(f"up_args {up_args} are not flags khgrl up takes (see khgrl up --help)") from None
    unset = vars(parser.parse_args([]))
    taken = sorted("--" + k.split("__")[-1].replace("_", "-") for k, v in given.items()  # (dests: cfg__tqc__x)
                   if k.split("__")[-1] in GRID_DESTS and (k not in unset or unset[k] != v))
    if taken:
        raise ValueError(f"up_args set {taken}: the grid sets these itself for each run")


def load_config(path: str | Path | None, overrides: dict) -> ExperimentConfig:
    """The config file's values (TOML or JSON), then every non-None override on top."""
    values: dict = {}
    if path is not None:
        values = read_table(path)  # the one reader of settings files (TOML or JSON)
        known = set(ExperimentConfig.__dataclass_fields__)
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"{path}: unknown keys {unknown}; known: {sorted(known)}")
    values.update({k: v for k, v in overrides.items() if v is not None})
    return ExperimentConfig(**values).validate()


def task_label(spec: str) -> str:
    """The name of a task's runs: ``fetch:moved`` -> ``fetch_moved``."""
    return re.sub(r"[^A-Za-z0-9_]", "_", spec)


@dataclass(frozen=True)
class RunSpec:
    scenario: str  # a passage-world scenario, or the label of a task (see ``task``)
    method: str
    seed: int
    task: str = ""  # the task spec, for runs of a task

    @property
    def name(self) -> str:
        return f"{self.scenario}-{self.method}-seed{self.seed}"


def plan_runs(cfg: ExperimentConfig) -> list[RunSpec]:
    """Seed-major order, so that an experiment cut short has every method and scenario at the same seeds."""
    if cfg.tasks:
        return [RunSpec(task_label(t), m, int(s), t) for s in cfg.seeds for t in cfg.tasks for m in cfg.methods]
    return [RunSpec(sc, m, int(s)) for s in cfg.seeds for sc in cfg.scenarios for m in cfg.methods]


def run_is_done(run_dir: Path, cfg: ExperimentConfig) -> bool:
    """Whether ``run_dir`` holds a finished run of ``cfg.episodes`` episodes, or one that ended early at
    ``cfg.until_success`` (then it is not redone)."""
    try:
        if cfg.system == "reference":
            summary = json.loads((run_dir / "summary.json").read_text())
            episodes = json.loads((run_dir / "episodes.json").read_text())
            return "wall_time_s" in summary and len(episodes) == cfg.episodes
        summary = json.loads((run_dir / "summary.json").read_text())
        actor = summary.get("a0", {})
        return (summary.get("failed") == [] and not summary.get("interrupted")
                and all(c == 0 for c in summary.get("exit_codes", {}).values())
                and (actor.get("episodes_in_run", actor.get("episodes")) == cfg.episodes  # (over all parts)
                     or actor.get("converged") is True)
                and actor.get("unconfirmed_transitions") == 0)
    except (OSError, ValueError, AttributeError):
        return False


def run_argv(spec: RunSpec, cfg: ExperimentConfig, run_dir: Path) -> list[str]:
    """The command of one run (the same a user types)."""
    khgrl = [sys.executable, "-m", "khgrl.deploy.cli"]
    if cfg.system == "reference":
        return [*khgrl, "reference", "--scenario", spec.scenario, "--method", spec.method, "--seed", str(spec.seed),
                "--episodes", str(cfg.episodes), "--run-dir", str(run_dir), "--quiet"]
    world = ["--task", spec.task] if spec.task else ["--scenario", spec.scenario]
    # kgrl_noadapt: --method kgrl --no-adapt; khgrl_rlpd: --sampling rlpd; hil-serl_episode: --takeover episode;
    # hil-serl_recipe: --recipe hil-serl (HIL-SERL's settings, teacher demonstrations, finishing takeover, task box)
    method, _, variant = spec.method.partition("_")
    argv = [*khgrl, "up", *world, "--method", method, "--seed", str(spec.seed),
            "--episodes", str(cfg.episodes), "--run-dir", str(run_dir), "--max-lead", str(cfg.max_lead),
            "--no-progress", *(["--no-adapt"] if variant == "noadapt" else []),
            *(["--sampling", "rlpd"] if variant == "rlpd" else []),
            *(["--takeover", "episode"] if variant == "episode" else []),
            *(["--recipe", "hil-serl"] if variant == "recipe" else [])]
    if method in HUMAN_METHODS:
        argv += ["--human", "scripted", "--human-episodes", *map(str, cfg.human_episodes)]
    else:
        argv += ["--human", "none"]
    if cfg.timeout > 0:
        argv += ["--timeout", str(cfg.timeout)]
    if cfg.until_success > 0:
        argv += ["--until-success", str(cfg.until_success), "--success-window", str(cfg.success_window)]
    return argv + list(cfg.up_args)
