"""A task made ready to run: its demonstrations checked, its LC-NS-KMP fitted under its hard constraints.

:func:`build_task_world` is where a task definition's mistakes surface as one :class:`~khgrl.common.tasks.api.TaskError`
(wrong shapes, non-finite demonstrations, constraints the KMP mean violates everywhere, a bad view) instead of
a traceback from deep inside the KMP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from khgrl.common.kmp.fit import KMPConfig, fit_model
from khgrl.common.kmp.lcnskmp import LCNSKMP
from khgrl.common.tasks.api import Task, TaskError, View, check_view, task_constraints, task_demos, vector

__all__ = ["TaskWorld", "build_task_world"]


@dataclass(frozen=True)
class TaskWorld:
    """Everything an episode of a task needs that does not change during a run."""

    task: Task
    demos: np.ndarray  # (M, N, O)
    model: LCNSKMP
    low: np.ndarray  # workspace box
    high: np.ndarray
    G: np.ndarray  # all hard constraints, G P >= c
    c: np.ndarray
    view: View
    default_scale: np.ndarray  # L0 (O,)

    @property
    def config(self) -> KMPConfig:
        return self.task.kmp

    @property
    def out_dim(self) -> int:
        return int(self.demos.shape[2])


def build_task_world(task: Task) -> TaskWorld:
    """Check ``task`` and fit its LC-NS-KMP.

    :param task: the task.
    :raises TaskError: naming what is wrong.
    """
    if not isinstance(task, Task):
        raise TaskError(f"expected a khgrl.common.tasks.api.Task, got {type(task).__name__}")
    demos = task_demos(task)
    o = demos.shape[2]
    low, high, G, c = task_constraints(task, o)
    scale = vector(task, "default_scale", task.default_scale, o)
    if np.any(scale <= 0):
        raise TaskError(f"task {task.name!r}: default_scale must be > 0, got {scale}")
    if not (np.isfinite(task.action_cost) and task.action_cost >= 0):
        raise TaskError(f"task {task.name!r}: action_cost must be a finite number >= 0, got {task.action_cost}")
    view = check_view(task, o)
    if not isinstance(task.kmp, KMPConfig):
        raise TaskError(f"task {task.name!r}: kmp must be a khgrl.common.kmp.fit.KMPConfig")
    try:
        model, _ = fit_model(demos, task.kmp, (G, c))
    except Exception as exc:  # noqa: BLE001 - GMM/KMP failures on odd data: say which task and why
        raise TaskError(f"task {task.name!r}: fitting the KMP to the demonstrations failed: "
                        f"{type(exc).__name__}: {exc}") from None
    mean = np.asarray(model.grid_mean)
    violated = np.all(mean @ G.T < c - 1e-9, axis=0)  # per constraint row: violated at every step
    if np.any(violated):
        k = int(np.argmax(violated))
        which = (f"workspace {'low' if k < o else 'high'} of output {k % o}" if k < 2 * o
                 else f"your constraint {k - 2 * o}")
        raise TaskError(f"task {task.name!r}: the KMP mean violates hard constraint {k}, {which} "
                        f"(G[{k}] = {G[k].tolist()}, c[{k}] = {c[k]:g}), at every step: the constraints contradict "
                        f"the demonstrations")
    _check_scripted_human(task, mean)
    return TaskWorld(task=task, demos=demos, model=model, low=low, high=high, G=G, c=c, view=view,
                     default_scale=scale)


def _check_scripted_human(task: Task, mean: np.ndarray) -> None:
    """Call the task's scripted human at every grid point of the KMP mean: it must give None or O finite values."""
    if task.scripted_human is None:
        return
    o = mean.shape[1]
    for t in range(mean.shape[0]):
        try:
            p_h = task.scripted_human(mean[t].copy())
        except Exception as exc:  # noqa: BLE001 - the user's function
            raise TaskError(f"task {task.name!r}: scripted_human raised {type(exc).__name__}: {exc} (for the KMP "
                            f"mean at step {t})") from None
        if p_h is None:
            continue
        arr = np.asarray(p_h, dtype=np.float64).reshape(-1) if np.ndim(p_h) <= 1 else np.zeros(0)
        if arr.shape != (o,) or not np.all(np.isfinite(arr)):
            raise TaskError(f"task {task.name!r}: scripted_human must return None or {o} finite values, got "
                            f"{p_h!r} for the KMP mean at step {t}")
