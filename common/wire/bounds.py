"""Value bounds of transitions: what the learner stores must be finite and within the run's task bounds
(:class:`~khgrl.common.wire.descriptor.TaskDescriptor`: ``obs_limits``, ``reward_bound``; actions in [-1, 1]).

A batch that passes the wire checks (finite numbers of the right sizes) may still hold values that wreck training:
a reward of 3e38 is a finite float32, but its square is not, and one such transition turned every parameter of the
learner's networks into NaN within one training iteration. :func:`check_bounds` is the learner's check of an
arriving batch (it refuses the whole batch, naming the first value out of bounds); :func:`bad_rows` is the same
check row by row for transitions already stored (a checkpoint's replay buffer, a journal replayed on resume), so
that the bad ones can be dropped and the rest kept.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

__all__ = ["check_bounds", "bad_rows", "limits", "ACTION_LIMIT", "NO_TASK_LIMIT"]

ACTION_LIMIT = 1.0 + 1e-6  # actions are in [-1, 1] (the wire check's tolerance)
NO_TASK_LIMIT = 1e12  # every value's bound where the task is not known (descriptor.MAX_BOUND)
_FIELDS = ("obs", "next_obs", "action", "reward")


def limits(task: Any, obs_dim: int) -> dict[str, tuple[np.ndarray | float, np.ndarray | float]]:
    """(low, high) per field: ``obs`` and ``next_obs`` within the task's ``obs_limits``, ``reward`` within
    +-``reward_bound``, ``action`` within [-1, 1]; without a task (None) every value within +-1e12.

    :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor`, or None
    :param obs_dim: the observation width (used without a task)
    """
    if task is None:
        obs: tuple = (np.full(obs_dim, -NO_TASK_LIMIT), np.full(obs_dim, NO_TASK_LIMIT))
        reward = NO_TASK_LIMIT
    else:
        obs, reward = task.obs_limits, float(task.reward_bound)
    return {"obs": obs, "next_obs": obs, "action": (-ACTION_LIMIT, ACTION_LIMIT), "reward": (-reward, reward)}


def _outside(arr: np.ndarray, low, high) -> np.ndarray:
    """(n, width) bool: the values outside [low, high] or not finite (NaN compares false)."""
    a = np.asarray(arr).reshape(len(arr), -1)
    return ~((a >= low) & (a <= high))  # (comparisons with NaN are false, and numpy does not warn of them)


def bad_rows(arrays: Mapping[str, np.ndarray], task: Any) -> np.ndarray:
    """Which transitions hold a value that is not finite or outside the task's bounds: a bool mask of the rows.

    :param arrays: ``obs`` and ``next_obs`` ((n, obs_dim), or SB3's (n, 1, obs_dim)), ``reward`` ((n,) or
        (n, 1)), optionally ``action`` ((n, O) or (n, 1, O)); any other key is ignored
    :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: only finiteness and
        +-1e12)
    """
    n = len(arrays["reward"])
    obs_dim = int(np.prod(np.shape(arrays["obs"])[1:]))
    bad = np.zeros(n, dtype=bool)
    for name, (low, high) in limits(task, obs_dim).items():
        if name in arrays:
            bad |= _outside(arrays[name], low, high).any(axis=1)
    return bad


def check_bounds(batch: Any, task: Any) -> str | None:
    """Why an arriving batch must be refused for its values (None: it may be stored): the first value that is not
    finite or lies outside the task's bounds, with its field, row, column and the bounds.

    :param batch: a :class:`~khgrl.common.wire.messages.Transitions` (its ``obs``, ``next_obs``, ``action``,
        ``reward``)
    :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: only finiteness and
        +-1e12)
    """
    for name, (low, high) in limits(task, batch.obs.shape[1]).items():
        if name == "action":  # (the wire's own check: finite and within [-1, 1])
            continue
        arr = getattr(batch, name)
        out = _outside(arr, low, high)
        if not out.any():
            continue
        row, col = (int(i) for i in np.argwhere(out)[0])
        value = float(np.asarray(arr).reshape(len(arr), -1)[row, col])
        lo, hi = (float(np.broadcast_to(b, out.shape[1:])[col]) for b in (low, high))
        where = f"{name}[{row}]" if name == "reward" else f"{name}[{row}, {col}]"
        what = "is not finite" if not np.isfinite(value) else f"= {value:.6g} is outside [{lo:.6g}, {hi:.6g}]"
        return f"{where} {what} ({int(out.any(axis=1).sum())} of {len(arr)} rows out of the task's bounds)"
    return None
