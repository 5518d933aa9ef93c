"""A task made ready to run: its demonstrations checked, its LC-NS-KMP fitted under its hard constraints.

:func:`build_task_world` is where a task definition's mistakes surface as one :class:`~khgrl.common.tasks.api.TaskError`
(wrong shapes, non-finite demonstrations, constraints the KMP mean violates everywhere, a bad view) instead of
a traceback from deep inside the KMP.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from khgrl.common.kmp.fit import KMPConfig, fit_model
from khgrl.common.kmp.lcnskmp import LCNSKMP
from khgrl.common.tasks.api import Task, TaskError, View, call_scripted_human, task_demos
from khgrl.common.tasks.checks import check_view, task_constraints, vector

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
    _check_demo_size(task, o)
    low, high, G, c = task_constraints(task, o)
    _check_feasible(task, G, c, o)
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
        raise TaskError(f"task {task.name!r}: the KMP mean violates hard constraint {k}, {_row_name(k, o)} "
                        f"(G[{k}] = {G[k].tolist()}, c[{k}] = {c[k]:g}), at every step: the constraints contradict "
                        f"the demonstrations")
    _check_scripted_human(task, model, mean)
    return TaskWorld(task=task, demos=demos, model=model, low=low, high=high, G=G, c=c, view=view,
                     default_scale=scale)


def _check_demo_size(task: Task, o: int) -> None:
    """Demonstrations from a file (``--demos FILE``, or the task's own file) against the task's own command size
    (its workspace's): a mismatch names the file first, the likely culprit (a wrong ``--demos``), not the workspace.
    (Demonstrations given as an array belong to the task definition: the workspace check says what is wrong.)"""
    if not isinstance(task.demos, (str, Path)):
        return
    if not (isinstance(task.workspace, (tuple, list)) and len(task.workspace) == 2):
        return  # task_constraints says what is wrong with the workspace
    sizes = {int(np.size(w)) for w in task.workspace if np.ndim(w) > 0}
    if len(sizes) == 1 and (k := sizes.pop()) != o:
        raise TaskError(f"task {task.name!r}: the demonstrations in {task.demos} have O = {o} outputs per step, but "
                        f"this task's command has {k} (its workspace has {k} values per bound): that file holds "
                        f"demonstrations of another task (--demos needs (M, N, {k}) for this one)")


def _row_name(k: int, o: int) -> str:
    """What row ``k`` of the task's G P >= c is: the workspace box (rows 0..2 O - 1) or the user's constraints."""
    if k < o:
        return f"workspace low of output {k}"
    if k < 2 * o:
        return f"workspace high of output {k - o}"
    return f"your constraint {k - 2 * o} (Task.constraints row {k - 2 * o})"


def _feasible(G: np.ndarray, c: np.ndarray) -> bool:
    """Whether {P : G P >= c} is non-empty (one LP)."""
    import scipy.optimize

    res = scipy.optimize.linprog(np.zeros(G.shape[1]), A_ub=-G, b_ub=-c, bounds=[(None, None)] * G.shape[1],
                                 method="highs")
    return res.status != 2


def _check_feasible(task: Task, G: np.ndarray, c: np.ndarray, o: int) -> None:
    """The hard constraints (workspace box and the user's, math.md §3) must admit a point. If they do not, name the
    rows that contradict each other: a deletion filter drops every row without which the rest is still infeasible,
    leaving an irreducible infeasible set (each of its rows is needed for the contradiction)."""
    if _feasible(G, c):
        return
    keep = list(range(len(c)))
    for k in range(len(c)):
        trial = [j for j in keep if j != k]
        if trial and not _feasible(G[trial], c[trial]):
            keep = trial
    rows = "; ".join(f"row {k}, {_row_name(k, o)}: {(np.round(G[k], 6) + 0.0).tolist()} . P >= {c[k]:g}" for k in keep)
    first, last = 2 * o, len(c) - 1
    yours = ("you gave no constraints" if last < first else f"row {first} is your constraint" if last == first
             else f"rows {first}..{last} are your constraints")
    raise TaskError(f"task {task.name!r}: the hard constraints G P >= c admit no point (rows 0..{2 * o - 1} are the "
                    f"workspace box, {yours}). These rows contradict each other: {rows}")


def _check_scripted_human(task: Task, model: LCNSKMP, mean: np.ndarray) -> None:
    """Call the task's scripted human at every grid point of the KMP mean (with the step, its phase and the robot at
    the mean; no observation yet): it must give None or O finite values."""
    if task.scripted_human is None:
        return
    o = mean.shape[1]
    phases = np.asarray(model.s[:, 0], dtype=np.float64)
    for t in range(mean.shape[0]):
        try:
            p_h = call_scripted_human(task.scripted_human, mean[t].copy(), step=t, phase=float(phases[t]),
                                      position=mean[t].copy(), obs=None)
        except Exception as exc:  # noqa: BLE001 - the user's function
            raise TaskError(f"task {task.name!r}: scripted_human raised {type(exc).__name__}: {exc} (for the KMP "
                            f"mean at step {t})") from None
        if p_h is None:
            continue
        arr = np.asarray(p_h, dtype=np.float64).reshape(-1) if np.ndim(p_h) <= 1 else np.zeros(0)
        if arr.shape != (o,) or not np.all(np.isfinite(arr)):
            raise TaskError(f"task {task.name!r}: scripted_human must return None or {o} finite values, got "
                            f"{p_h!r} for the KMP mean at step {t}")
