"""The one source of a run's settings: frozen dataclasses, the ``--flags`` built from them, and TOML/JSON files.

* :class:`TQCSettings` -- the paper's TQC settings (Section IV); the learner and the single-process baseline
  both build their model from :meth:`TQCSettings.sb3_kwargs`. They are the learner's settings whatever its
  algorithm (``RunConfig.algo``, ``--algo``): another algorithm takes those that apply to it.
* :class:`StreamSettings` -- the transition stream and its flow control (batch size, lead limit, outbox,
  timeouts, checkpoint interval).
* :class:`~khgrl.common.config.safety.SafetySettings` -- what the actor does to keep a robot safe (rate limits on
  P_t, the watchdog).
* :class:`RunConfig` -- a whole run: world, method, episodes, seed, processes, and the three above.

Every field has its default, its help text and its roles here, once: the commands whose flags it is (``up``
takes every setting; ``learner``, ``actor``, ``human`` and ``reference`` those whose roles name them).
:func:`add_config_flags` turns the fields of a role into command-line flags (``learning_starts`` ->
``--learning-starts``) whose help shows the default; :func:`resolve` merges defaults < a config file < flags
and validates the result. ``khgrl up`` writes the resolved configuration into the run directory (``config.toml``,
and ``config.json`` with the run's runtime facts: run id, router endpoint, actor ids); every child process reads
that file instead of a hand-built argv, and ``khgrl up --config RUN_DIR/config.toml`` runs the same configuration
again.

A table becomes the dataclass in :mod:`khgrl.common.config.tables` (types and choices checked there).

One module of ~330 lines on purpose: the dataclasses and the flags built from them must stay together: a flag is a
field.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import zlib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, get_type_hints

from khgrl.common.config.assignments import parse_assignments
from khgrl.common.config.fields import _LA, _LAH, ACTOR, HUMAN, LEARNER, REFERENCE, ROLES, UP, _opt
from khgrl.common.config.files import load_file, read_table, to_toml, write_run_config
from khgrl.common.config.hilserl import PRESET, RECIPES, HilSerlSettings
from khgrl.common.config.safety import SafetySettings
from khgrl.common.config.tables import build, merge
from khgrl.common.config.tqc import SAMPLINGS, TQCSettings

__all__ = ["METHODS", "HUMAN_METHODS", "REFERENCE_METHODS", "SAMPLINGS", "HILSERL_DEFAULTS", "HUMANS",
           "PAPER_EPISODES", "ROLES", "TQCSettings", "StreamSettings", "SafetySettings", "RunConfig",
           "add_config_flags", "role_fields", "parse_assignments", "resolve", "read_table", "load_file",
           "write_run_config", "read_run_file", "to_toml"]

METHODS = ("khgrl", "kgrl", "hil-serl")
HUMAN_METHODS, REFERENCE_METHODS = ("khgrl", "hil-serl"), ("khgrl", "kgrl")  # with a human; khgrl reference's
TAKEOVERS = ("steps", "episode", "finish")
HILSERL_DEFAULTS = {"algo": "sac_ln", "tqc": {"sampling": "rlpd"}}  # what --method hil-serl implies unless set
MODES = ("simulation", "robot")
PHYSICAL = ("off", "detect", "scripted")
# khgrl human's clients (test_config checks)
HUMANS = ("scripted", "gui", "keyboard", "gamepad", "spacemouse", "replay", "none")
PAPER_EPISODES = (4, 5, 10, 19, 20, 28, 29)  # Section IV: episodes with human corrections (counted from 1)

@dataclass(frozen=True)
class StreamSettings:
    """The transition stream from actors to the learner (docs/protocol.md, "Flow control")."""

    batch: int = _opt(8, "transitions per batch (cut at multiples of the actor's running index; the learner stores "
                         "no more than max_lead + 2 batches of an actor ahead of training)", roles=_LA)
    max_lead: int = _opt(8, "transitions an actor may run ahead of what the learner trained on "
                            "(8 = the train frequency: step-for-step single-process SB3)", roles=_LA)
    window: int = _opt(64, "batches an actor has out beyond what the learner acknowledged (the rest wait)",
                       roles=(ACTOR,))
    mode: str = _opt("simulation", "simulation: actors wait for the learner (max_lead, the paper's update-to-data "
                                   "ratio); robot: actors never wait, the learner trains as fast as it can", MODES,
                     roles=_LA)
    outbox_memory: int = _opt(1000, "batches an actor keeps in memory before spilling them to disk", roles=(ACTOR,))
    resend_after_s: float = _opt(2.0, "re-send un-acknowledged batches after this long without ack progress (s)",
                                 roles=(ACTOR,))
    flush_timeout: float = _opt(120.0, "at the end, an actor waits this long for the learner to confirm (s)",
                                roles=(ACTOR,))
    correction_timeout: float = _opt(0.5, "a silent correction client loses the robot after this (s)", roles=(ACTOR,))
    human_pause_s: float = _opt(60.0, "a human-input client's pause ends after this unless the client renews it by "
                                      "asking again (s; 0: until it resumes)", roles=(ACTOR,))
    human_hold_s: float = _opt(60.0, "a human-input client's holding allowance per actor, in seconds of the actor's "
                                     "running time: the longest hold; it refills at human_hold_refill (0: unlimited)",
                               roles=(ACTOR,))
    human_hold_refill: float = _opt(0.5, "seconds of holding allowance a client regains per second it does not hold "
                                         "(a client holds at most refill / (1 + refill) of a long run)",
                                    roles=(ACTOR,))
    learner_wait: float = _opt(10.0, "at start, an actor waits this long for a learner before acting without one, "
                                     "so processes started together are in lock-step from the first step (s)",
                               roles=(ACTOR,))
    journal: bool = _opt(True, "the learner journals every batch it stores (append-only, fsync'd segments in "
                               "CHECKPOINT_DIR/journal): a batch is durable for its actor within milliseconds; "
                               "--no-journal: only full checkpoints make batches durable", roles=(LEARNER,))
    checkpoint_every: int = _opt(0, "full learner checkpoint (model and whole replay buffer) every N ingested "
                                    "transitions; 0: with the journal, once it holds a replay buffer's worth since "
                                    "the last one; always at the end, and without the journal when an actor asks",
                                 roles=(LEARNER,))
    model_checkpoint_every: int = _opt(250, "the learner saves its model (model.zip and state.json, no replay "
                                            "buffer) every N training iterations (0: only with full checkpoints)",
                                       roles=(LEARNER,))
    lease_ms: int = _opt(3000, "Zenoh link lease: how fast a dead process is noticed (ms)", roles=_LAH)

    def validate(self, train_freq: int) -> None:
        if self.batch < 1 or self.outbox_memory < 1 or self.window < 1:
            raise ValueError("batch, window and outbox_memory must be >= 1")
        if self.max_lead < train_freq:
            # the learner trains at multiples of train_freq: a smaller lead could wait forever after a short
            # end-of-episode batch
            raise ValueError(f"max_lead must be >= the learner's train frequency ({train_freq})")
        if min(self.checkpoint_every, self.model_checkpoint_every) < 0 or self.lease_ms < 500 or self.learner_wait < 0:
            raise ValueError("checkpoint_every, model_checkpoint_every and learner_wait must be >= 0 and lease_ms "
                             ">= 500")
        if self.human_pause_s < 0 or self.human_hold_s < 0 or self.human_hold_refill <= 0:
            raise ValueError("human_pause_s and human_hold_s must be >= 0 and human_hold_refill > 0")


@dataclass(frozen=True)
class RunConfig:
    """One run of ``khgrl up``: every setting of every process. Field order is the order of ``--help``."""

    task: str = _opt("", "the task: passage:SCENARIO, fetch:control|moved|random|obstacle, panda:pick, or "
                         "package.module:callable returning a khgrl.task.Task (README, 'Bring your own task')",
                     roles=(ACTOR, HUMAN), shown="passage:<scenario>")
    scenario: str = _opt("high_cov", "passage-world scenario (shorthand for --task passage:SCENARIO)",
                         roles=(ACTOR, HUMAN, REFERENCE))
    demos: str = _opt("", "demonstrations instead of the task's: a file (.npz/.csv, M x N x O) or a local LeRobot "
                          "dataset, lerobot:PATH[?feature=observation.state&dims=A:B&n=N] (one episode per "
                          "demonstration, linearly interpolated over its phase to the task's N points; README, "
                          "'LeRobot datasets')", roles=(ACTOR, HUMAN))
    method: str = _opt("khgrl", "khgrl: human corrections and a learned exploration scale; kgrl: neither; hil-serl: "
                                "the HIL-SERL baseline (delta actions in the task's own space, no KMP band; the "
                                "human takes over; implies --algo sac_ln --sampling rlpd unless given)", METHODS,
                       roles=(ACTOR, HUMAN, REFERENCE))
    physical: str = _opt("off", "physical corrections: detect (the actor takes a push on the arm, seen in its "
                                "measured position, as the human's P_h), scripted (and, in simulation, a scripted "
                                "physical human pushes the arm in the human episodes: a task with a push hook, "
                                "e.g. panda:pick) or off", PHYSICAL, roles=(ACTOR,))
    adapt: bool = _opt(True, "refit the KMP through the via-points of a task whose scene changes every episode, at "
                             "every reset (a task with a Scene; --no-adapt: the demonstrations' KMP in every scene)",
                       roles=(ACTOR,))
    algo: str = _opt("tqc", "the learner's algorithm, by its name in khgrl.learner.algorithm.REGISTRY (tqc: "
                            "sb3-contrib TQC, the paper's; it takes the [tqc] settings that apply to it)",
                     roles=(LEARNER, ACTOR))
    episodes: int = _opt(60, "episodes per actor (a resumed run continues up to this)", roles=(ACTOR, REFERENCE))
    until_success: float = _opt(0.0, "end an actor's run early once its last --success-window autonomous episodes "
                                     "(no human step) succeed at this rate or more (0: run every episode)",
                                roles=(ACTOR,))
    success_window: int = _opt(20, "autonomous episodes --until-success looks back over", roles=(ACTOR,))
    seed: int = _opt(0, "seed of the learner and of actor 0 (actor i: seed + i) and the human client",
                     roles=(*_LAH, REFERENCE))
    run_dir: str = _opt("runs/demo", "run directory (refused if it holds results, unless --resume/--overwrite)",
                        roles=_LAH)
    run: str = _opt("", "run id, the key prefix khgrl/<run>/", roles=_LAH, shown="derived from the run directory")
    actors: int = _opt(1, "number of actor processes", roles=())
    human: str = _opt("scripted", "human-input client (khgrl only): scripted, gui (a window to drag the robot), "
                                  "keyboard, gamepad, spacemouse (move the desired position with keys / a stick / "
                                  "a 3Dconnexion SpaceMouse), replay (a recorded session, --replay FILE), none",
                        HUMANS, roles=())
    human_clients: str = _opt("", "which actors each human-input client may correct and pause: "
                                  "'CLIENT=ACTOR[,ACTOR...]' entries separated by ';' (CLIENT=*: every actor; a client "
                                  "not listed: none)", roles=(ACTOR,), shown="every client, every actor")
    human_episodes: tuple[int, ...] = _opt(PAPER_EPISODES, "episodes with scripted corrections (the paper's)",
                                           roles=(HUMAN, ACTOR, REFERENCE))
    takeover: str = _opt("steps", "--method hil-serl: the scripted human takes over in the steps it corrects KhGRL "
                                  "in (steps), in every step of its episodes, on the KMP mean elsewhere (episode), or "
                                  "from its first correction of an episode to the episode's end (finish)",
                         TAKEOVERS, roles=(HUMAN,))
    recipe: str = _opt("none", "none: the protocol every method shares; hil-serl: HIL-SERL's recipe (implies --method "
                               "hil-serl, its published settings, --takeover finish, 20 teacher demonstrations, the "
                               "task-sized safety box, unless given; common/config/hilserl.py)", RECIPES,
                       roles=(LEARNER, ACTOR, HUMAN))
    human_noise: float = _opt(0.0, "std of the scripted human's hand noise (workspace units)",
                              roles=(HUMAN, REFERENCE))
    replay: str = _opt("", "with --human replay: the recorded RUN_DIR/actor-ID/corrections.csv to feed in",
                       roles=(HUMAN,))
    connect: str = _opt("", "join the router at this endpoint (tcp/HOST:PORT) instead of starting one", roles=_LAH)
    port: int = _opt(0, "port of the router khgrl up starts on 127.0.0.1 (0: a free one)", roles=())
    connect_timeout: float = _opt(15.0, "fail if the router cannot be reached within this many seconds",
                                  roles=_LAH)
    rate: float = _opt(0.0, "actor control rate in Hz (0: as fast as flow control allows)", roles=(ACTOR,))
    actor_rt_priority: int = _opt(0, "actors' control loops under SCHED_FIFO at this priority "
                                     "(1-99; needs --rate and root; 0: off)", roles=(ACTOR,))
    learner_nice: int = _opt(5, "learner nice level, so training yields the CPU to the actors' control loops",
                             roles=(LEARNER,))
    learner_threads: int = _opt(1, "torch CPU threads of the learner", roles=(LEARNER,))
    checkpoint_dir: str = _opt("", "where the learner keeps its checkpoints, e.g. a data disk", roles=(LEARNER,),
                               shown="RUN_DIR/learner")
    tensorboard: bool = _opt(True, "write TensorBoard scalars (learner/tb, actor-ID/tb)", roles=_LA)
    timeout: float = _opt(0.0, "fail the run after this many seconds (0: none)", roles=())
    stop_timeout: float = _opt(60.0, "seconds the processes get to stop cleanly", roles=())
    tqc: TQCSettings = field(default_factory=TQCSettings)
    stream: StreamSettings = field(default_factory=StreamSettings)
    safety: SafetySettings = field(default_factory=SafetySettings)
    hilserl: HilSerlSettings = field(default_factory=HilSerlSettings)

    def validate(self) -> "RunConfig":
        if self.episodes < 1 or self.actors < 1:
            raise ValueError("episodes and actors must be >= 1")
        if not 0.0 <= self.until_success <= 1.0 or self.success_window < 1:
            raise ValueError("until_success must be in [0, 1] and success_window >= 1")
        if self.run and (any(c in self.run for c in "/*$?# ") or len(self.run) > 64):
            raise ValueError(f"run id must be a key chunk without / * $ ? # or space, got {self.run!r}")
        if self.actor_rt_priority and not (1 <= self.actor_rt_priority <= 99 and self.rate > 0):
            raise ValueError("actor_rt_priority must be in 1..99 and needs rate > 0 (a real-time loop must sleep)")
        if self.task and ":" not in self.task:
            raise ValueError(f"task {self.task!r}: expected 'passage:SCENARIO' or 'package.module:callable'")
        if any(e < 1 for e in self.human_episodes):
            raise ValueError("human_episodes are counted from 1")
        parse_assignments(self.human_clients)  # (raises ValueError naming a bad entry)
        if self.human == "replay" and self.method == "khgrl" and not self.replay:
            raise ValueError("human 'replay' needs replay: the corrections.csv of a recorded run (--replay FILE)")
        if self.physical != "off" and self.method not in HUMAN_METHODS:
            raise ValueError(f"physical corrections need a method with a human ({', '.join(HUMAN_METHODS)})")
        if self.connect_timeout <= 0 or self.rate < 0:
            raise ValueError("connect_timeout must be > 0 and rate >= 0")
        if not self.algo.isidentifier():
            raise ValueError(f"algo {self.algo!r}: expected the name of a registered learner algorithm, e.g. tqc")
        self.tqc.validate()
        self.stream.validate(self.tqc.train_freq)
        self.safety.validate(self.stream.correction_timeout)
        self.hilserl.validate()
        if self.recipe != "none" and self.method != "hil-serl":
            raise ValueError(f"recipe {self.recipe!r} is an option of method hil-serl, not {self.method!r}")
        return self

    @property
    def task_spec(self) -> str:
        """The task this run uses: ``task``, or the passage world's ``scenario``."""
        return self.task or f"passage:{self.scenario}"

    def actor_ids(self) -> list[str]:
        return [f"a{i}" for i in range(self.actors)]

    def actor_seed(self, actor_id: str) -> int:
        """``a<i>``: ``seed + i`` (counted in ``actors`` or not); another id: ``seed`` + its CRC-32 mod 10^6. Two
        actors never collect the same transitions (the learner would refuse the second's as replays).

        :param actor_id: the actor's id
        """
        m = re.fullmatch(r"a(0|[1-9][0-9]{0,8})", actor_id)
        return self.seed + (int(m.group(1)) if m else zlib.crc32(actor_id.encode()) % 1_000_000)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# ------------------------------------------------------------------------------------ flags
def _flag_fields(cls=RunConfig, prefix: tuple[str, ...] = ()):
    """(path, field, type) of every setting of ``cls``, nested settings flattened."""
    hints = get_type_hints(cls)
    for f in fields(cls):
        typ = hints[f.name]
        if is_dataclass(typ):
            yield from _flag_fields(typ, (*prefix, f.name))
        else:
            yield (*prefix, f.name), f, typ


def role_fields(role: str) -> list[str]:
    """The names of the settings that are flags of command ``role`` (one of :data:`ROLES`), in ``--help`` order."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; roles are {ROLES}")
    return [path[-1] for path, f, _ in _flag_fields() if role in f.metadata["roles"]]


def _help(f) -> str:
    """The help text and, once, the default (``shown`` where it needs words)."""
    d = f.default
    shown = f.metadata["shown"] or (" ".join(map(str, d)) if isinstance(d, tuple) else (d if d != "" else "none"))
    return f"{f.metadata['help']} (default: {shown})"


def add_config_flags(parser: argparse.ArgumentParser, role: str = UP) -> None:
    """Add a flag for every setting of command ``role`` (:data:`ROLES`; ``up``: every setting). A flag given on the
    command line overrides the config file; the help text shows the default."""
    names = set(role_fields(role))
    group = parser.add_argument_group("run settings (override --config)")
    for path, f, typ in _flag_fields():
        if path[-1] not in names:
            continue
        kw: dict[str, Any] = {"dest": "cfg__" + "__".join(path), "default": argparse.SUPPRESS, "help": _help(f)}
        if typ is bool:
            kw["action"] = argparse.BooleanOptionalAction
        elif isinstance(f.default, tuple):
            kw.update(type=int, nargs="+")
        else:
            kw["type"] = typ if typ in (int, float, str) else str
        if f.metadata.get("choices"):
            kw["choices"] = f.metadata["choices"]
        elif typ is not bool:
            kw["metavar"] = path[-1].upper()
        group.add_argument("--" + path[-1].replace("_", "-"), **kw)


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


def resolve(config_file: str | Path | None = None, args: argparse.Namespace | None = None,
            overrides: dict | None = None) -> RunConfig:
    """Defaults < ``config_file`` < flags in ``args`` (from :func:`add_config_flags`) < ``overrides``;
    validated (:class:`ValueError` names the bad setting)."""
    data = load_file(config_file) if config_file else {}
    if args is not None:
        data = merge(data, _overrides(args))
    if overrides:
        data = merge(data, overrides)
    if data.get("recipe") == "hil-serl":  # HIL-SERL's recipe (common/config/hilserl.py), unless set
        data = merge(PRESET, data)
    if data.get("method") == "hil-serl":  # the recipe's algorithm and sampling, unless set
        data = merge(HILSERL_DEFAULTS, data)
    return build(RunConfig, data, "config").validate()


def read_run_file(path: str | Path) -> tuple[RunConfig, dict]:
    """A run's ``config.json`` as written by :func:`write_run_config`: (settings, runtime)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"run configuration {path} does not exist")
    data = json.loads(path.read_text())
    runtime = data.pop("runtime", {}) if isinstance(data, dict) else {}
    return build(RunConfig, data, str(path)).validate(), runtime
