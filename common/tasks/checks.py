"""The checks of a task's parts (:class:`~khgrl.common.tasks.api.Task`): numbers, the workspace box and the hard
constraints, the drawing hints and the value bounds the learner holds its transitions to (the demonstrations are
checked where they are loaded, :func:`~khgrl.common.tasks.api.task_demos`). Each mistake is one
:class:`~khgrl.common.tasks.api.TaskError` naming the task and the part; ``build_task_world`` calls them when a task
is built."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from khgrl.common.tasks.api import MAX_DECLARED_BOUND, Task, TaskError, View
from khgrl.common.wire.descriptor import MAX_BOUND

__all__ = ["vector", "task_constraints", "check_view", "value_bounds"]


def vector(task: Task, what: str, value: Any, dim: int | None = None) -> np.ndarray:
    """``value`` as a finite float64 vector (of ``dim`` entries, if given), or a :class:`TaskError`."""
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise TaskError(f"task {task.name!r}: {what} is not numeric ({exc})") from None
    if dim is not None and arr.size == 1 and dim > 1 and np.ndim(value) == 0:
        arr = np.full(dim, float(arr[0]))
    if dim is not None and arr.shape != (dim,):
        raise TaskError(f"task {task.name!r}: {what} needs {dim} values (one per output), got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise TaskError(f"task {task.name!r}: {what} is not finite: {arr}")
    return arr


def task_constraints(task: Task, o: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(low, high, G, c): the workspace box and all hard constraints as G P >= c (box rows first)."""
    from khgrl.common.kmp.fit import box_constraints

    if not (isinstance(task.workspace, (tuple, list)) and len(task.workspace) == 2):
        raise TaskError(f"task {task.name!r}: workspace must be (low, high)")
    low = vector(task, "workspace low", task.workspace[0], o)
    high = vector(task, "workspace high", task.workspace[1], o)
    if np.any(low >= high):
        raise TaskError(f"task {task.name!r}: workspace needs low < high in every output, got {low} and {high}")
    G, c = box_constraints(low, high)
    if task.constraints is not None:
        try:
            G2 = np.asarray(task.constraints[0], dtype=np.float64)
            c2 = np.asarray(task.constraints[1], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError, IndexError) as exc:
            raise TaskError(f"task {task.name!r}: constraints must be (G, c) arrays ({exc})") from None
        if G2.ndim != 2 or G2.shape[1] != o or c2.shape != (G2.shape[0],):
            raise TaskError(f"task {task.name!r}: constraints need G of shape (K, {o}) and c of shape (K,), got "
                            f"{G2.shape} and {c2.shape}")
        if not (np.all(np.isfinite(G2)) and np.all(np.isfinite(c2))):
            raise TaskError(f"task {task.name!r}: constraints are not finite")
        G, c = np.concatenate([G, G2]), np.concatenate([c, c2])
    return low, high, G, c


def check_view(task: Task, o: int) -> View:
    """The task's drawing hints checked against O (axes in range, shapes of O coordinates)."""
    v = task.view
    axes = tuple(v.axes)
    if len(axes) != 2 or any(not (0 <= a < o) for a in axes) or (o > 1 and axes[0] == axes[1]):
        raise TaskError(f"task {task.name!r}: view axes {axes} must be two different outputs in 0..{o - 1}")
    if v.third is not None and not (0 <= v.third < o):
        raise TaskError(f"task {task.name!r}: view third axis {v.third} is not an output in 0..{o - 1}")
    names = tuple(v.names) or tuple(("x", "y", "z")[k] if k < 3 else f"y{k}" for k in range(o))
    if len(names) != o:
        raise TaskError(f"task {task.name!r}: view names {names} need one name per output ({o})")
    for s in v.shapes:
        coords = {"box": ("low", "high"), "sphere": ("center",), "point": ("at",)}.get(getattr(s, "kind", None))
        if coords is None:
            raise TaskError(f"task {task.name!r}: view shape {s!r} is not a Cuboid, Sphere or Point")
        for c in coords:
            vector(task, f"shape {s.name!r} {c}", getattr(s, c), o)
    return replace(v, axes=axes, names=names)


def value_bounds(task: Task, workspace: tuple[np.ndarray, np.ndarray],
                 obs_space: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """(reward bound, observation bound) of the task's descriptor: the learner refuses a transition whose |reward|
    or |observation| is beyond them (or whose observation lies outside its space by more than a tenth of the
    space's width). The reward bound is the environment's (``task.reward_bound``) plus the largest action cost
    the workspace allows: ``4 * action_cost * |high - low|^2`` (|P_t - eta0_t| <= twice the workspace's diagonal,
    even where the KMP mean leaves the box a little).

    :param task: the task (its ``reward_bound``, ``obs_bound`` -- stated or derived:
        :func:`~khgrl.common.tasks.derived_bounds.resolve_bounds` -- and ``action_cost``).
    :param workspace: (low, high) of the workspace box.
    :param obs_space: (low, high) of the policy's observation space (infinite where unbounded).
    :raises TaskError: a declared bound that is not a number in (0, 1e9], or an observation space that lies
        entirely beyond +-obs_bound in some dimension.
    """
    for what, v in (("reward_bound", task.reward_bound), ("obs_bound", task.obs_bound)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= MAX_DECLARED_BOUND:
            raise TaskError(f"task {task.name!r}: {what} must be a number in (0, {MAX_DECLARED_BOUND:g}], got {v!r}")
    bound = float(task.obs_bound)
    low, high = (np.asarray(x, dtype=np.float64) for x in obs_space)
    outside = np.flatnonzero((low > bound) | (high < -bound))
    if outside.size:
        k = int(outside[0])
        raise TaskError(f"task {task.name!r}: observation {k}'s space [{low[k]:g}, {high[k]:g}] lies beyond "
                        f"obs_bound {bound:g}: declare a larger Task(obs_bound=...)")
    span = np.asarray(workspace[1], dtype=np.float64) - np.asarray(workspace[0], dtype=np.float64)
    action_cost = 4.0 * float(task.action_cost) * float(span @ span)
    return min(float(task.reward_bound) + action_cost, MAX_BOUND), bound
