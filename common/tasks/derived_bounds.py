"""Value bounds for a task that does not state them (``Task(reward_bound=None)`` or ``obs_bound=None``, the
default): derived from what its environment shows, with a stated margin, instead of a fixed 1e6.

The learner refuses a batch whose |reward| or |observation| lies beyond the task's bounds
(:mod:`khgrl.common.wire.bounds`). A fixed default of 1e6 is far from any task: the passage world's rewards stay
within +-220, and an actor holding the run's keys could store rewards of 999,000 that the critic then learns (Q on
the honest actor's states went from -15 to +2.4 million, issue 34 point 5). So a task that does not state a bound
gets one from its environment:

* replay each demonstration as the command (through ``Task.command`` where the task has one), then
  :data:`EPISODES` random episodes (a demonstration plus a random walk whose steps are at most the demonstrations'
  largest step, kept in the workspace box), all from ``make_env(SEED)`` reset with :data:`SEED` -- the same
  numbers in every process, so the launcher, each actor and the learner agree on the task digest;
* the bound is :data:`MARGIN` (4) times the largest finite |value| seen, rounded up to a power of two, and at
  least :data:`FLOOR` (1). (The policy's observation adds the phase in [0, 1] and the deviation in [-1, 1].)

:data:`RULE` says this in one line; ``khgrl up`` writes it with the bounds into the run's ``config.json``
(``runtime.task_bounds``). A task whose transitions may go beyond what its demonstrations and a random episode
show (a bonus they never reach, a sensor with a wider range) should state its bounds; a real robot should too,
since deriving them drives the environment. The built-in tasks state theirs.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from khgrl.common.tasks.api import Task, TaskError
from khgrl.common.tasks.obs_spaces import state_of

__all__ = ["MARGIN", "FLOOR", "EPISODES", "SEED", "RULE", "SeenRanges", "seen_ranges", "margin_bound",
           "resolve_bounds"]

log = logging.getLogger("khgrl.task")

MARGIN = 4.0  # a derived bound is this times the largest |value| seen, rounded up to a power of two
FLOOR = 1.0  # the smallest derived bound
EPISODES = 2  # random episodes after the demonstrations
SEED = 0  # the environment's and the random episodes' seed (the same in every process)
RULE = (f"{MARGIN:g} x the largest |value| seen replaying the demonstrations and {EPISODES} random episodes "
        f"(seed {SEED}), rounded up to a power of two (at least {FLOOR:g})")


@dataclass(frozen=True)
class SeenRanges:
    """What a task's environment showed: the largest finite |reward| and |observation| (any dimension)."""

    reward: float
    obs: float
    steps: int


def margin_bound(value: float) -> float:
    """:data:`MARGIN` x ``value`` rounded up to a power of two, at least :data:`FLOOR`.

    :param value: the largest |value| seen (>= 0).
    """
    v = MARGIN * max(float(value), 0.0)
    return max(FLOOR, 2.0 ** math.ceil(math.log2(v))) if v > 0 else FLOOR


def _walk(demos: np.ndarray, low: np.ndarray, high: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Random episode ``k``: demonstration ``k % M`` plus a random walk of steps up to the demos' largest step."""
    step = np.abs(np.diff(demos, axis=1)).max(axis=(0, 1))
    offsets = np.cumsum(rng.uniform(-step, step, size=demos.shape[1:]), axis=0)
    return np.clip(demos[k % len(demos)] + offsets, low, high)


def _run(task: Task, env: Any, commands: np.ndarray, seen: list[float]) -> int:
    """One episode of ``env`` driven by ``commands`` (N, O); the largest |reward| and |obs| into ``seen``."""
    obs, _ = env.reset(seed=SEED)
    _note(seen, 1, state_of(task, obs))
    steps = 0
    for p in commands:
        action = task.command(env, p.copy()) if task.command is not None else p.copy()
        obs, reward, terminated, truncated, _ = env.step(action)
        _note(seen, 0, reward)
        _note(seen, 1, state_of(task, obs))  # a task with cameras: its state vector (the images are uint8)
        steps += 1
        if terminated or truncated:
            break
    return steps


def _note(seen: list[float], k: int, value: Any) -> None:
    a = np.abs(np.asarray(value, dtype=np.float64).reshape(-1))
    a = a[np.isfinite(a)]
    if a.size:
        seen[k] = max(seen[k], float(a.max()))


def seen_ranges(task: Task, demos: np.ndarray, low: np.ndarray, high: np.ndarray) -> SeenRanges:
    """Replay the demonstrations and :data:`EPISODES` random episodes in a fresh environment (the module docstring).

    :param task: the task (its ``make_env`` and ``command``).
    :param demos: its checked demonstrations (M, N, O).
    :param low: the workspace box's lower corner (O,).
    :param high: its upper corner.
    :raises TaskError: the environment raised while being replayed.
    """
    rng = np.random.default_rng(SEED)
    seen, steps = [0.0, 0.0], 0
    try:
        env = task.make_env(SEED)
        try:
            for m in range(len(demos)):
                steps += _run(task, env, demos[m], seen)
            for k in range(EPISODES):
                steps += _run(task, env, _walk(demos, low, high, k, rng), seen)
        finally:
            if hasattr(env, "close"):
                env.close()
    except Exception as exc:  # noqa: BLE001 - the user's environment
        raise TaskError(f"task {task.name!r}: deriving its value bounds (it states no reward_bound or obs_bound), "
                        f"the environment raised {type(exc).__name__}: {exc}") from None
    return SeenRanges(reward=seen[0], obs=seen[1], steps=steps)


def resolve_bounds(task: Task, demos: np.ndarray, low: np.ndarray, high: np.ndarray) -> tuple[Task, dict]:
    """``task`` with both bounds set (those it states kept, the others derived: :func:`seen_ranges`,
    :func:`margin_bound`), and a record of how (``khgrl up`` writes it into ``config.json``).

    :param task: the task.
    :param demos: its checked demonstrations (M, N, O).
    :param low: the workspace box's lower corner (O,).
    :param high: its upper corner.
    """
    if task.reward_bound is not None and task.obs_bound is not None:
        return task, {"reward_bound": task.reward_bound, "obs_bound": task.obs_bound, "rule": "stated by the task"}
    seen = seen_ranges(task, demos, np.asarray(low, np.float64), np.asarray(high, np.float64))
    reward = task.reward_bound if task.reward_bound is not None else margin_bound(seen.reward)
    obs = task.obs_bound if task.obs_bound is not None else margin_bound(max(seen.obs, 1.0))
    derived = [n for n, v in (("reward_bound", task.reward_bound), ("obs_bound", task.obs_bound)) if v is None]
    log.info("task %s: %s derived (%s): largest |reward| %.4g, |observation| %.4g in %d steps -> reward_bound %g, "
             "obs_bound %g", task.name, " and ".join(derived), RULE, seen.reward, seen.obs, seen.steps, reward, obs)
    record = {"reward_bound": reward, "obs_bound": obs, "derived": derived, "rule": RULE,
              "seen": {"reward": seen.reward, "obs": seen.obs, "steps": seen.steps}}
    return replace(task, reward_bound=reward, obs_bound=obs), record
