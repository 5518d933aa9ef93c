"""The one source of a run's settings: frozen dataclasses, the ``--flags`` built from them, and TOML/JSON files.

* :class:`TQCSettings` -- the paper's TQC settings (Section IV); the learner and the single-process baseline
  both build their model from :meth:`TQCSettings.sb3_kwargs`. They are the learner's settings whatever its
  algorithm (``RunConfig.algo``, ``--algo``): another algorithm takes those that apply to it.
* :class:`StreamSettings` -- the transition stream and its flow control (batch size, lead limit, outbox,
  timeouts, checkpoint interval).
* :class:`RunConfig` -- a whole run: world, method, episodes, seed, processes, and the two above.

Every field has its default and its help text here, once. :func:`add_config_flags` turns the fields into
command-line flags (``learning_starts`` -> ``--learning-starts``) whose help shows the default;
:func:`resolve` merges defaults < a config file < flags and validates the result. ``khgrl up`` writes the
resolved configuration into the run directory (``config.toml``, and ``config.json`` with the run's runtime
facts: run id, router endpoint, actor ids); every child process reads that file instead of a hand-built argv,
and ``khgrl up --config RUN_DIR/config.toml`` runs the same configuration again.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tomllib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, get_type_hints

from khgrl.common.tasks.passage.scenarios import SCENARIOS as _PASSAGE_SCENARIOS

__all__ = ["SCENARIOS", "METHODS", "HUMANS", "PAPER_EPISODES", "TQCSettings", "StreamSettings", "RunConfig",
           "add_config_flags", "resolve", "load_file", "write_run_config", "read_run_file", "to_toml"]

SCENARIOS = tuple(_PASSAGE_SCENARIOS)  # the passage world's scenarios: "high_cov", "low_cov"
METHODS = ("khgrl", "kgrl")
DEVICES = ("auto", "cpu", "cuda")
MODES = ("simulation", "robot")
HUMANS = ("scripted", "gui", "keyboard", "gamepad", "none")
PAPER_EPISODES = (4, 5, 10, 19, 20, 28, 29)  # Section IV: episodes with human corrections (counted from 1)


def _opt(default: Any, help: str, choices: tuple | None = None, flag: bool = True):  # noqa: A002
    """A config field: its default, help text, allowed values, and whether it is a command-line flag."""
    meta = {"help": help, "choices": choices, "flag": flag}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults (frozen settings)")
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class TQCSettings:
    """sb3-contrib TQC as in the paper (Section IV): 2 x 256, lr 1e-3, tau 0.02, gamma 0.99, train_freq 8,
    gradient_steps 8, automatic entropy coefficient."""

    learning_rate: float = _opt(1e-3, "TQC learning rate")
    tau: float = _opt(0.02, "soft target update rate")
    gamma: float = _opt(0.99, "discount factor")
    train_freq: int = _opt(8, "transitions per training iteration")
    gradient_steps: int = _opt(8, "gradient steps per training iteration")
    ent_coef: str = _opt("auto", "entropy coefficient ('auto': learned)")
    net_arch: tuple[int, ...] = _opt((256, 256), "hidden layer sizes of actor and critics")
    learning_starts: int = _opt(100, "uniform random actions (and no training) for the first N transitions")
    batch_size: int = _opt(256, "minibatch size of a gradient step")
    buffer_size: int = _opt(200_000, "replay buffer capacity (transitions)")
    device: str = _opt("auto", "where the learner trains: auto (cuda if torch sees a GPU, else cpu), cpu or cuda; "
                               "weights always go to actors as CPU float32 arrays", DEVICES)

    def sb3_kwargs(self, seed: int) -> dict[str, Any]:
        """Keyword arguments of ``sb3_contrib.TQC("MlpPolicy", env, **kwargs)``."""
        return dict(learning_rate=self.learning_rate, tau=self.tau, gamma=self.gamma, train_freq=self.train_freq,
                    gradient_steps=self.gradient_steps, ent_coef=self.ent_coef,
                    policy_kwargs=dict(net_arch=list(self.net_arch)), learning_starts=self.learning_starts,
                    batch_size=self.batch_size, buffer_size=self.buffer_size, seed=seed, device=self.device,
                    verbose=0)

    def validate(self) -> None:
        for name in ("train_freq", "gradient_steps", "batch_size", "buffer_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.learning_starts < 0 or not self.net_arch or min(self.net_arch) < 1:
            raise ValueError("learning_starts must be >= 0 and net_arch a list of positive sizes")


@dataclass(frozen=True)
class StreamSettings:
    """The transition stream from actors to the learner (docs/protocol.md, "Flow control")."""

    batch: int = _opt(8, "transitions per batch (cut at multiples of the actor's running index)")
    max_lead: int = _opt(8, "transitions an actor may run ahead of what the learner trained on "
                            "(8 = the train frequency: step-for-step single-process SB3)")
    window: int = _opt(64, "batches an actor has out beyond what the learner acknowledged (the rest wait)")
    mode: str = _opt("simulation", "simulation: actors wait for the learner (max_lead, the paper's update-to-data "
                                   "ratio); robot: actors never wait, the learner trains as fast as it can", MODES)
    outbox_memory: int = _opt(1000, "batches an actor keeps in memory before spilling them to disk")
    resend_after_s: float = _opt(2.0, "re-send un-acknowledged batches after this long without ack progress (s)")
    flush_timeout: float = _opt(120.0, "at the end, an actor waits this long for the learner to confirm (s)")
    correction_timeout: float = _opt(0.5, "a silent correction client loses the robot after this (s)")
    learner_wait: float = _opt(10.0, "at start, an actor waits this long for a learner before acting without one, "
                                     "so processes started together are in lock-step from the first step (s)")
    checkpoint_every: int = _opt(2000, "learner checkpoint every N ingested transitions (0: only at the end)")
    lease_ms: int = _opt(3000, "Zenoh link lease: how fast a dead process is noticed (ms)")

    def validate(self, train_freq: int) -> None:
        if self.batch < 1 or self.outbox_memory < 1 or self.window < 1:
            raise ValueError("batch, window and outbox_memory must be >= 1")
        if self.max_lead < train_freq:
            # the learner trains at multiples of train_freq: a smaller lead could wait forever after a short
            # end-of-episode batch
            raise ValueError(f"max_lead must be >= the learner's train frequency ({train_freq})")
        if self.checkpoint_every < 0 or self.lease_ms < 500 or self.learner_wait < 0:
            raise ValueError("checkpoint_every and learner_wait must be >= 0 and lease_ms >= 500")


@dataclass(frozen=True)
class RunConfig:
    """One run of ``khgrl up``: every setting of every process. Field order is the order of ``--help``."""

    task: str = _opt("", "the task: passage:SCENARIO or package.module:callable returning a khgrl.task.Task "
                         "(README, 'Bring your own task'; default: passage:<scenario>)")
    scenario: str = _opt("high_cov", "passage-world scenario (shorthand for --task passage:SCENARIO)", SCENARIOS)
    demos: str = _opt("", "demonstration file (.npz/.csv, M x N x O) replacing the task's demonstrations")
    method: str = _opt("khgrl", "khgrl: human corrections and a learned exploration scale; kgrl: neither", METHODS)
    algo: str = _opt("tqc", "the learner's algorithm, by its name in khgrl.learner.algorithm.REGISTRY (tqc: "
                            "sb3-contrib TQC, the paper's; it takes the [tqc] settings that apply to it)")
    episodes: int = _opt(60, "episodes per actor (in the whole run: a resumed run continues up to this)")
    seed: int = _opt(0, "seed of the learner and of actor 0 (actor i: seed + i) and the human client")
    run_dir: str = _opt("runs/demo", "run directory (refused if it holds results, unless --resume/--overwrite)")
    run: str = _opt("", "run id, the key prefix khgrl/<run>/ (default: derived from the run directory)")
    actors: int = _opt(1, "number of actor processes")
    human: str = _opt("scripted", "human-input client (khgrl only): scripted, gui (a window to drag the robot), "
                                  "keyboard, gamepad (move the desired position with keys / a stick), none", HUMANS)
    human_episodes: tuple[int, ...] = _opt(PAPER_EPISODES, "episodes with scripted corrections (the paper's)")
    human_noise: float = _opt(0.0, "std of the scripted human's hand noise (workspace units)")
    connect: str = _opt("", "join the router at this endpoint (tcp/HOST:PORT) instead of starting one")
    port: int = _opt(0, "port of the router khgrl up starts on 127.0.0.1 (0: a free one)")
    connect_timeout: float = _opt(15.0, "fail if the router cannot be reached within this many seconds")
    rate: float = _opt(0.0, "actor control rate in Hz (0: as fast as flow control allows)")
    actor_rt_priority: int = _opt(0, "actors' control loops under SCHED_FIFO at this priority "
                                     "(1-99; needs --rate and root; 0: off)")
    learner_nice: int = _opt(5, "learner nice level, so training yields the CPU to the actors' control loops")
    learner_threads: int = _opt(1, "torch CPU threads of the learner")
    checkpoint_dir: str = _opt("", "where the learner keeps its checkpoints, e.g. a data disk (none: RUN_DIR/learner)")
    tensorboard: bool = _opt(True, "write TensorBoard scalars (learner/tb, actor-ID/tb)")
    timeout: float = _opt(0.0, "fail the run after this many seconds (0: none)")
    stop_timeout: float = _opt(60.0, "seconds the processes get to stop cleanly")
    tqc: TQCSettings = field(default_factory=TQCSettings)
    stream: StreamSettings = field(default_factory=StreamSettings)

    def validate(self) -> "RunConfig":
        if self.episodes < 1 or self.actors < 1:
            raise ValueError("episodes and actors must be >= 1")
        if self.run and (any(c in self.run for c in "/*$?# ") or len(self.run) > 64):
            raise ValueError(f"run id must be a key chunk without / * $ ? # or space, got {self.run!r}")
        if self.actor_rt_priority and not (1 <= self.actor_rt_priority <= 99 and self.rate > 0):
            raise ValueError("actor_rt_priority must be in 1..99 and needs rate > 0 (a real-time loop must sleep)")
        if self.task and ":" not in self.task:
            raise ValueError(f"task {self.task!r}: expected 'passage:SCENARIO' or 'package.module:callable'")
        if any(e < 1 for e in self.human_episodes):
            raise ValueError("human_episodes are counted from 1")
        if self.connect_timeout <= 0 or self.rate < 0:
            raise ValueError("connect_timeout must be > 0 and rate >= 0")
        if not self.algo.isidentifier():
            raise ValueError(f"algo {self.algo!r}: expected the name of a registered learner algorithm, e.g. tqc")
        self.tqc.validate()
        self.stream.validate(self.tqc.train_freq)
        return self

    @property
    def task_spec(self) -> str:
        """The task this run uses: ``task``, or the passage world's ``scenario``."""
        return self.task or f"passage:{self.scenario}"

    def actor_ids(self) -> list[str]:
        return [f"a{i}" for i in range(self.actors)]

    def actor_seed(self, actor_id: str) -> int:
        """Actor ``a<i>`` is seeded with ``seed + i`` (any other id: ``seed``)."""
        ids = self.actor_ids()
        return self.seed + (ids.index(actor_id) if actor_id in ids else 0)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# ------------------------------------------------------------------------------------ flags
def _flag_fields(cls=RunConfig, prefix: tuple[str, ...] = ()):
    """(path, field, type) of every flag field of ``cls``, nested settings flattened."""
    hints = get_type_hints(cls)
    for f in fields(cls):
        typ = hints[f.name]
        if is_dataclass(typ):
            yield from _flag_fields(typ, (*prefix, f.name))
        elif f.metadata.get("flag", True):
            yield (*prefix, f.name), f, typ


def _flag_name(path: tuple[str, ...]) -> str:
    return "--" + path[-1].replace("_", "-")


def add_config_flags(parser: argparse.ArgumentParser, only: set[str] | None = None) -> None:
    """Add a flag for every field (or those in ``only``, by field name). A flag given on the command line
    overrides the config file; the help text shows the default."""
    group = parser.add_argument_group("run settings (override --config)")
    for path, f, typ in _flag_fields():
        if only is not None and path[-1] not in only:
            continue
        kw: dict[str, Any] = {"dest": "cfg__" + "__".join(path), "default": argparse.SUPPRESS}
        default = f.default
        shown = " ".join(map(str, default)) if isinstance(default, tuple) else (default if default != "" else "none")
        kw["help"] = f"{f.metadata['help']} (default: {shown!s})"
        if typ is bool:
            kw["action"] = argparse.BooleanOptionalAction
        elif isinstance(default, tuple):
            kw.update(type=int, nargs="+")
        else:
            kw["type"] = typ if typ in (int, float, str) else str
        if typ is not bool and not f.metadata.get("choices"):
            kw["metavar"] = path[-1].upper()
        if f.metadata.get("choices"):
            kw["choices"] = f.metadata["choices"]
        group.add_argument(_flag_name(path), **kw)


def _overrides(args: argparse.Namespace) -> dict:
    out: dict = {}
    for name, value in vars(args).items():
        if name.startswith("cfg__"):
            *tables, key = name[5:].split("__")
            d = out
            for t in tables:
                d = d.setdefault(t, {})
            d[key] = value
    return out


# ------------------------------------------------------------------------------------ files
def load_file(path: str | Path) -> dict:
    """A run config file: TOML (``.toml``) or JSON (``.json``; ``runtime`` is kept apart, see read_run_file)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {path} does not exist")
    if path.suffix == ".json":
        data = json.loads(path.read_text())
    else:
        with open(path, "rb") as fh:
            try:
                data = tomllib.load(fh)
            except tomllib.TOMLDecodeError as exc:
                raise ValueError(f"{path}: not valid TOML: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a table of settings")
    data.pop("runtime", None)
    return data


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out.get(k, {}), v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _coerce(value: Any, typ: Any, where: str) -> Any:
    if typ is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true/false, got {value!r}")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}: expected an integer, got {value!r}")
        return value
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if typ is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}: expected a string, got {value!r}")
        return value
    if not isinstance(value, (list, tuple)):  # tuple[int, ...]
        raise ValueError(f"{where}: expected a list of integers, got {value!r}")
    return tuple(_coerce(v, int, where) for v in value)


def _build(cls, data: dict, where: str):
    hints = get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown setting(s) {', '.join(unknown)}")
    kw = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        typ, value = hints[f.name], data[f.name]
        if is_dataclass(typ):
            if not isinstance(value, dict):
                raise ValueError(f"{where}.{f.name}: expected a table")
            kw[f.name] = _build(typ, value, f"{where}.{f.name}")
            continue
        kw[f.name] = _coerce(value, typ, f"{where}.{f.name}")
        choices = f.metadata.get("choices")
        if choices and kw[f.name] not in choices:
            raise ValueError(f"{where}.{f.name}: {kw[f.name]!r} is not one of {', '.join(choices)}")
    return cls(**kw)


def resolve(config_file: str | Path | None = None, args: argparse.Namespace | None = None,
            overrides: dict | None = None) -> RunConfig:
    """Defaults < ``config_file`` < flags in ``args`` (from :func:`add_config_flags`) < ``overrides``;
    validated (:class:`ValueError` names the bad setting)."""
    data = load_file(config_file) if config_file else {}
    if args is not None:
        data = _merge(data, _overrides(args))
    if overrides:
        data = _merge(data, overrides)
    return _build(RunConfig, data, "config").validate()


# ------------------------------------------------------------------------------------ writing
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def to_toml(cfg: RunConfig) -> str:
    """The configuration as TOML, each setting with its help as a comment (reads back to the same config)."""
    lines = ["# KhGRL run configuration (khgrl up --config FILE); every flag of khgrl up overrides it.", ""]

    def table(obj, name: str | None) -> None:
        if name:
            lines.extend(["", f"[{name}]"])
        for f in fields(obj):
            v = getattr(obj, f.name)
            if is_dataclass(v):
                continue
            lines.append(f"# {f.metadata['help']}")
            lines.append(f"{f.name} = {_toml_value(v)}")

    table(cfg, None)
    for f in fields(cfg):
        if is_dataclass(getattr(cfg, f.name)):
            table(getattr(cfg, f.name), f.name)
    return "\n".join(lines) + "\n"


def write_run_config(run_dir: str | Path, cfg: RunConfig, runtime: dict) -> Path:
    """``RUN_DIR/config.toml`` (the resolved settings) and ``RUN_DIR/config.json`` (the same plus ``runtime``:
    run id, endpoint, actor ids, command line, start time) -- the file every child process reads."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.toml").write_text(to_toml(cfg))
    path = run_dir / "config.json"
    path.write_text(json.dumps({**cfg.to_dict(), "runtime": runtime}, indent=2))
    return path


def read_run_file(path: str | Path) -> tuple[RunConfig, dict]:
    """A run's ``config.json`` as written by :func:`write_run_config`: (settings, runtime)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"run configuration {path} does not exist")
    data = json.loads(path.read_text())
    runtime = data.pop("runtime", {}) if isinstance(data, dict) else {}
    return _build(RunConfig, data, str(path)).validate(), runtime
