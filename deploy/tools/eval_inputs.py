"""The pieces of ``khgrl eval`` (:mod:`khgrl.deploy.tools.evaluate`): what it reads (the run's settings,
checkpoint, task
and learned scale), where it writes (:func:`free_path`) and one deterministic rollout (:func:`run_episode`)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

__all__ = ["EvalError", "EpisodeResult", "free_path", "find_run", "read_config", "find_model", "load_run_task",
           "load_scale", "load_policy", "checkpoint_algo", "trained", "run_episode"]


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


def load_run_task(cfg: Any, cwd: str | None = None, spec: str | None = None) -> tuple[Any, str]:
    """The run's task (``--task`` / ``--scenario``, ``--demos``) and its spec.

    :param cfg: the run's :class:`~khgrl.common.config.settings.RunConfig`.
    :param cwd: the directory ``khgrl up`` ran in, if the run recorded it: the task's module and a relative
        ``--demos`` path are also looked for there.
    :param spec: another task to load with the run's demonstrations (None: the run's).
    :raises EvalError: the task does not load.
    """
    from khgrl.common.tasks.api import TaskError, load_task

    demos = cfg.demos or None
    if cwd and Path(cwd).is_dir():
        if cwd not in sys.path:
            sys.path.append(cwd)
        if demos is not None and not demos.startswith("lerobot:") and not Path(demos).exists():
            demos = str(Path(cwd) / demos)
    spec = spec or cfg.task_spec
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


def checkpoint_algo(model_zip: Path, cfg: Any) -> str:
    """The algorithm that wrote the checkpoint (its ``state.json``), else the run's ``--algo``."""
    try:
        saved = json.loads((model_zip.parent / "state.json").read_text()).get("algo")
    except (OSError, ValueError, AttributeError):
        saved = None
    return saved or getattr(cfg, "algo", "tqc")


def trained(model_zip: Path) -> dict:
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
