"""``khgrl eval RUN_DIR``: how well a trained policy does on its own -- deterministic episodes, no human, no
learning.

``RUN_DIR``: any run directory with a learner checkpoint and an actor folder (``khgrl up``'s, or processes started
by hand with one ``--run-dir``), or that actor folder (``RUN_DIR/actor-a0``). The settings (task, ``--demos``,
network) come from ``RUN_DIR/config.json`` (``khgrl up``), else the actor's ``actor-ID/config.json`` (written when
it ends); the policy from the learner's checkpoint; the exploration scale L from the actor's ``scale_model.json``
(KhGRL: the L the policy was trained with; missing, L0 and a warning line). Each episode is reset with ``seed + i``;
the policy acts deterministically (the mean action). Output: a per-episode table and success rate / return mean ±
std on stdout, a CSV (``RUN_DIR/eval/eval.csv`` by default; never overwritten: ``eval-2.csv``, ...), and with
``--gif`` an animation of the first episode (:mod:`khgrl.common.tasks.render`). A missing or unusable run
directory, checkpoint or task is one line and exit 2.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["EvalError", "EpisodeResult", "Evaluation", "evaluate", "add_parser", "free_path", "report", "find_run"]

GIF_MAX_FRAMES = 100  # the first episode is subsampled to about this many frames (~16 kB each)


class EvalError(RuntimeError):
    """An evaluation that cannot run (no config, no checkpoint, a task that does not load); one line."""


@dataclass(frozen=True)
class EpisodeResult:
    """One evaluated episode (a row of the CSV)."""

    episode: int
    seed: int
    steps: int
    ret: float  # the KGRLEnv reward: the task environment's plus the action cost r_a
    env_return: float  # the task environment's reward alone
    action_cost: float  # sum of r_a (<= 0)
    success: bool
    terminated: bool


@dataclass
class Evaluation:
    """What :func:`evaluate` did: the episodes, and where it read and wrote."""

    task: str
    spec: str
    checkpoint: Path
    trained: dict
    scale: str
    episodes: list[EpisodeResult]
    csv: Path | None = None
    gif: Path | None = None
    gif_frames: int = 0
    settings: Path | None = None  # the config.json the run's settings came from
    warning: str = ""  # e.g. a KhGRL run evaluated without its learned scale

    @property
    def success_rate(self) -> float:
        return float(np.mean([e.success for e in self.episodes])) if self.episodes else 0.0

    def returns(self) -> np.ndarray:
        return np.array([e.ret for e in self.episodes], dtype=np.float64)


# ------------------------------------------------------------------------------------ inputs
def free_path(path: Path) -> Path:
    """``path`` if nothing is there, else ``stem-2.ext``, ``stem-3.ext``, ... (never overwrite a result).

    :param path: the wanted file.
    """
    path = Path(path)
    k = 2
    candidate = path
    while candidate.exists():
        candidate = path.with_name(f"{path.stem}-{k}{path.suffix}")
        k += 1
    return candidate


def find_run(path: str | Path, actor: str | None = None) -> tuple[Path, str]:
    """(run directory, actor id) of what ``khgrl eval`` was given: a run directory, or an actor folder in one
    (``RUN_DIR/actor-ID``: its parent and that actor, unless ``actor`` names another).

    :param path: ``RUN_DIR`` or ``RUN_DIR/actor-ID``.
    :param actor: the actor asked for (None: ``a0``, or the folder's).
    """
    p = Path(path)
    is_actor_dir = p.name.startswith("actor-") and any((p / f).is_file() for f in ("config.json", "episodes.csv"))
    if is_actor_dir and not (p / "learner").is_dir():
        return p.parent, actor or p.name[len("actor-"):]
    return p, actor or "a0"


def read_config(run_dir: Path, actor: str = "a0") -> tuple[Any, dict, Path]:
    """The run's settings and runtime facts: from ``RUN_DIR/config.json`` (``khgrl up``), else from the actor's
    ``RUN_DIR/actor-ID/config.json`` (processes started by hand; that actor's, else any actor's), and the file.

    :param run_dir: the run directory.
    :param actor: the actor whose file is preferred.
    :raises EvalError: no such file, or it does not parse.
    """
    from khgrl.common.config.settings import read_run_file

    run_dir = Path(run_dir)
    candidates = [run_dir / "config.json", run_dir / f"actor-{actor}" / "config.json",
                  *sorted(run_dir.glob("actor-*/config.json"))]
    path = next((c for c in candidates if c.is_file()), None)
    if path is None:
        raise EvalError(f"{run_dir}: no config.json there nor in an actor folder (khgrl up writes RUN_DIR/config.json, "
                        f"an actor RUN_DIR/actor-ID/config.json when it ends): nothing says which task the run had")
    try:
        cfg, runtime = read_run_file(path)
    except (ValueError, OSError) as exc:
        raise EvalError(f"{path}: {exc}") from None
    return cfg, runtime, path


def find_model(run_dir: Path, checkpoint: str | Path | None) -> Path:
    """The ``model.zip`` to evaluate: ``--checkpoint`` (a checkpoint directory, a learner directory or a
    model.zip) or the run's most trained complete learner checkpoint (full or model checkpoint).

    :param run_dir: the run directory.
    :param checkpoint: what ``--checkpoint`` gave (None: the run's).
    :raises EvalError: nothing to load.
    """
    from khgrl.learner.checkpoint import MODEL_FILE, newest_model

    if checkpoint is None:  # (the full checkpoint or the model checkpoint, whichever is trained more)
        found = newest_model(Path(run_dir) / "learner")
        if found is None or not (found / MODEL_FILE).is_file():
            raise EvalError(f"{run_dir}: no learner checkpoint in {Path(run_dir) / 'learner'} "
                            "(did the run train? give --checkpoint PATH)")
        return found / MODEL_FILE
    p = Path(checkpoint)
    for cand in (p, p / MODEL_FILE, p / "checkpoint" / MODEL_FILE):
        if cand.is_file():
            return cand
    raise EvalError(f"--checkpoint {checkpoint}: no {MODEL_FILE} there")


def load_run_task(cfg: Any, cwd: str | None = None) -> tuple[Any, str]:
    """The run's task (``--task`` / ``--scenario``, ``--demos``) and its spec.

    :param cfg: the run's :class:`~khgrl.common.config.settings.RunConfig`.
    :param cwd: the directory ``khgrl up`` ran in, if the run recorded it: the task's module and a relative
        ``--demos`` path are also looked for there.
    :raises EvalError: the task does not load.
    """
    from khgrl.common.tasks.api import TaskError, load_task

    demos = cfg.demos or None
    if cwd and Path(cwd).is_dir():
        if cwd not in sys.path:
            sys.path.append(cwd)
        demos = demos if demos is None or Path(demos).exists() else str(Path(cwd) / demos)
    spec = cfg.task_spec
    try:
        return load_task(spec, demos), spec
    except TaskError as exc:
        raise EvalError(str(exc)) from None


def load_scale(run_dir: Path, actor: str, dim: int) -> tuple[Any, str]:
    """The exploration scale model an actor of the run ended with (``actor-ID/scale_model.json``), or None
    (the task's L0), and a few words saying which.

    :param run_dir: the run directory.
    :param actor: the actor id.
    :param dim: the task's command size O.
    """
    from khgrl.common.kmp.scale import ScaleModel

    path = Path(run_dir) / f"actor-{actor}" / "scale_model.json"
    if not path.is_file():
        return None, "L0 (no learned scale)"
    try:
        model = ScaleModel.from_dict(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError) as exc:
        raise EvalError(f"{path}: not a scale model ({exc})") from None
    if model.dim != dim:
        raise EvalError(f"{path}: a scale for {model.dim} outputs, the task has {dim}")
    if model.n_points == 0:
        return model, "L0 (never refitted)"
    return model, f"learned by actor-{actor} ({model.n_points} points)"


def load_policy(model_zip: Path, env: Any, settings: Any, algo: str = "tqc") -> Any:
    """The policy of a learner checkpoint on ``env``'s spaces, in evaluation mode, loaded through the learner-algorithm
    interface (:meth:`~khgrl.learner.algorithm.LearnerAlgorithm.checkpoint_policy`).

    :param model_zip: the learner's ``model.zip``.
    :param env: the evaluation environment (its spaces).
    :param settings: the run's learner settings (``TQCSettings``: network sizes).
    :param algo: the algorithm that wrote the checkpoint (``--algo``).
    :raises EvalError: the file does not load or does not fit the task's spaces.
    """
    from khgrl.learner.algorithm import algorithm_class

    try:
        return algorithm_class(algo).checkpoint_policy(model_zip, env.observation_space, env.action_space, settings)
    except ValueError as exc:
        raise EvalError(f"{model_zip}: {exc}") from None


def _checkpoint_algo(model_zip: Path, cfg: Any) -> str:
    """The algorithm that wrote the checkpoint (its ``state.json``), else the run's ``--algo``."""
    try:
        saved = json.loads((model_zip.parent / "state.json").read_text()).get("algo")
    except (OSError, ValueError, AttributeError):
        saved = None
    return saved or getattr(cfg, "algo", "tqc")


def _trained(model_zip: Path) -> dict:
    """Counters of the checkpoint's ``state.json`` (transitions, gradient steps, weights version)."""
    path = model_zip.parent / "state.json"
    try:
        state = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return {k: state[k] for k in ("total_ingested", "gradient_steps", "version") if k in state}


# ------------------------------------------------------------------------------------ rollouts
def run_episode(env: Any, policy: Any, episode: int, seed: int,
                on_step: Callable[[Any, bool], None] | None = None) -> EpisodeResult:
    """One deterministic episode without a human.

    :param env: a :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
    :param policy: the policy (:class:`~khgrl.learner.algorithm.ActorPolicy`).
    :param episode: the episode number (from 1).
    :param seed: the reset seed.
    :param on_step: ``on_step(env, done)`` after the reset and after every step (the GIF's frames).
    """
    obs, _ = env.reset(seed=seed)
    if on_step is not None:
        on_step(env, False)
    ret = cost = 0.0
    steps, success, terminated, done = 0, False, False, False
    while not done:
        action, _ = policy.predict(obs, deterministic=True)
        obs, r, terminated, truncated, info = env.step(action)
        ret += float(r)
        cost += float(info["r_a"])
        steps += 1
        success = success or bool(info.get("success", False))
        done = terminated or truncated
        if on_step is not None:
            on_step(env, done)
    return EpisodeResult(episode=episode, seed=seed, steps=steps, ret=ret, env_return=ret - cost, action_cost=cost,
                         success=success, terminated=bool(terminated))


def _write_csv(path: Path, episodes: list[EpisodeResult]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["episode", "seed", "steps", "return", "env_return", "action_cost", "success", "terminated"])
        for e in episodes:
            w.writerow([f"{v:.10g}" if isinstance(v, float) else v for v in asdict(e).values()])


def evaluate(run_dir: str | Path, checkpoint: str | Path | None = None, episodes: int = 10, seed: int | None = None,
             gif: str | Path | None = None, csv_path: str | Path | None = None,
             actor: str | None = None) -> Evaluation:
    """Evaluate a run's policy (see the module docstring).

    :param run_dir: the run directory (or an actor folder in it: :func:`find_run`).
    :param checkpoint: a checkpoint directory or model.zip (None: the run's learner checkpoint).
    :param episodes: episodes to run.
    :param seed: seed of the first episode's reset (episode i: seed + i - 1; None: the run's seed).
    :param gif: write an animation of the first episode here (None: none).
    :param csv_path: the CSV of the episodes (None: RUN_DIR/eval/eval.csv); an existing file is not overwritten.
    :param actor: the actor whose learned exploration scale is used (None: a0, or the actor folder's).
    :raises EvalError: one line saying what is missing.
    """
    import torch
    from khgrl.common.tasks.api import TaskError
    from khgrl.common.tasks.kgrl_env import KGRLEnv
    from khgrl.common.tasks.world import build_task_world

    if episodes < 1:
        raise EvalError("--episodes must be >= 1")
    run_dir, actor = find_run(run_dir, actor)
    cfg, runtime, settings = read_config(run_dir, actor)
    model_zip = find_model(run_dir, checkpoint)
    task, spec = load_run_task(cfg, runtime.get("cwd"))
    seed = cfg.seed if seed is None else int(seed)
    torch.manual_seed(seed)
    try:
        world = build_task_world(task)
        scale_model, scale_text = load_scale(run_dir, actor, world.out_dim)
        env = KGRLEnv(world=world, seed=seed, scale_model=scale_model)
    except TaskError as exc:
        raise EvalError(str(exc)) from None
    policy = load_policy(model_zip, env, cfg.tqc, _checkpoint_algo(model_zip, cfg))
    result = Evaluation(task=task.name, spec=spec, checkpoint=model_zip.parent, trained=_trained(model_zip),
                        scale=scale_text, episodes=[], settings=settings,
                        warning=_scale_warning(cfg, task, scale_model, run_dir / f"actor-{actor}"))
    from khgrl.deploy.gif import GifRecorder

    recorder = GifRecorder(env, every=-(-env.horizon // GIF_MAX_FRAMES)) if gif else None
    with torch.no_grad():
        for i in range(episodes):
            result.episodes.append(run_episode(env, policy, i + 1, seed + i, recorder if i == 0 else None))
    env.close()
    result.csv = free_path(Path(csv_path) if csv_path else run_dir / "eval" / "eval.csv")
    _write_csv(result.csv, result.episodes)
    if recorder is not None:
        result.gif = free_path(Path(gif))
        result.gif_frames = recorder.save(result.gif)
    return result


def _scale_warning(cfg: Any, task: Any, scale_model: Any, actor_dir: Path) -> str:
    """The line saying a KhGRL run is evaluated without its learned scale (its policy trained under it, III-C)."""
    if cfg.method != "khgrl" or not task.learn_scale or scale_model is not None:
        return ""
    return (f"warning: {actor_dir / 'scale_model.json'} is missing: evaluating with the task's default scale L0, not "
            f"the scale this KhGRL run learned from the human (give the run directory, or the actor folder, of the "
            f"actor whose scale to use: --actor ID)")


# ------------------------------------------------------------------------------------ command
def report(ev: Evaluation) -> str:
    """The text ``khgrl eval`` prints: the inputs, one line per episode, the summary and the files.

    :param ev: the evaluation.
    """
    trained = ", ".join(f"{k} {v}" for k, v in ev.trained.items()) or "no state.json"
    source = f"; settings from {ev.settings}" if ev.settings and ev.settings.parent.name.startswith("actor-") else ""
    lines = [ev.warning] if ev.warning else []
    lines += [f"task {ev.task} ({ev.spec}){source}; checkpoint {ev.checkpoint} ({trained}); scale {ev.scale}",
             f"{'episode':>7} {'seed':>6} {'steps':>6} {'return':>10} {'env':>10} {'r_a':>9}  success"]
    for e in ev.episodes:
        lines.append(f"{e.episode:>7} {e.seed:>6} {e.steps:>6} {e.ret:>10.2f} {e.env_return:>10.2f} "
                     f"{e.action_cost:>9.2f}  {'yes' if e.success else 'no'}")
    r = ev.returns()
    n_ok = sum(e.success for e in ev.episodes)
    lines.append(f"success {n_ok}/{len(ev.episodes)} ({100 * ev.success_rate:.0f} %); return {r.mean():.2f} ± "
                 f"{r.std():.2f}; steps {np.mean([e.steps for e in ev.episodes]):.1f}")
    lines.append(f"wrote {ev.csv}")
    if ev.gif is not None:
        lines.append(f"wrote {ev.gif} ({ev.gif_frames} frames of episode 1)")
    return "\n".join(lines)


def _cmd_eval(args: argparse.Namespace) -> int:
    if args.gif and "DISPLAY" not in os.environ:
        os.environ.setdefault("MUJOCO_GL", "egl")  # (before MuJoCo is imported) offscreen camera views
    try:
        ev = evaluate(args.run_dir, checkpoint=args.checkpoint, episodes=args.episodes, seed=args.seed,
                      gif=args.gif, csv_path=args.csv, actor=args.actor)
    except EvalError as exc:
        print(f"khgrl eval: error: {exc}", file=sys.stderr)
        return 2
    print(report(ev))
    return 0


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``khgrl eval`` on the subcommands ``sub`` of the ``khgrl`` parser.

    :param sub: the ``add_subparsers()`` object.
    """
    p = sub.add_parser("eval", help="run a trained policy deterministically (no human, no learning): success "
                                    "rate, returns, CSV, GIF")
    p.add_argument("run_dir", metavar="RUN_DIR",
                   help="a run directory with a learner checkpoint and an actor folder (khgrl up's, or processes "
                        "started by hand with one --run-dir), or its actor folder RUN_DIR/actor-ID")
    p.add_argument("--checkpoint", default=None, metavar="PATH",
                   help="a learner checkpoint directory or model.zip (default: RUN_DIR/learner/checkpoint)")
    p.add_argument("--episodes", type=int, default=10, help="episodes (default: %(default)s)")
    p.add_argument("--seed", type=int, default=None,
                   help="reset seed of the first episode, episode i gets SEED + i - 1 (default: the run's seed)")
    p.add_argument("--gif", default=None, metavar="FILE", help="animate episode 1 into this GIF (default: none)")
    p.add_argument("--csv", default=None, metavar="FILE",
                   help="per-episode results (default: RUN_DIR/eval/eval.csv; never overwritten: eval-2.csv, ...)")
    p.add_argument("--actor", default=None, metavar="ID",
                   help="use the exploration scale this actor learned (default: a0, or the actor folder's)")
    p.set_defaults(func=_cmd_eval)
    return p

