"""What an actor announces about its task: the :class:`~khgrl.common.wire.descriptor.TaskDescriptor` of a
:class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` (its world, spaces, bounds, view and KMP)."""

from __future__ import annotations

from typing import Any

import numpy as np
from khgrl.common.tasks.checks import value_bounds
from khgrl.common.tasks.derived_bounds import resolve_bounds
from khgrl.common.tasks.obs_spaces import STATE

__all__ = ["descriptor", "task_bounds"]


def task_bounds(env: Any) -> tuple[Any, dict]:
    """The env's task with both value bounds set (stated, or derived once per env:
    :func:`~khgrl.common.tasks.derived_bounds.resolve_bounds`) and the record of how.

    :param env: the :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
    """
    found = getattr(env, "_resolved_bounds", None)
    if found is None or found[0] is not env.task:
        w = env.world
        found = (env.task, *resolve_bounds(env.task, w.demos, w.low, w.high))
        env._resolved_bounds = found
    return found[1], found[2]


def descriptor(env: Any, spec: str = ""):
    """The run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor`.

    :param env: the :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
    :param spec: the task's spec as given (``passage:low_cov``, ``module:callable``; default: its name).

    A task with cameras: the observation fields (``obs_dim``, ``obs_low``, ``obs_high``, ``obs_bound``) describe the
    policy observation's ``"state"`` vector; ``cameras`` names its images and their (H, W, C) (issue 37).
    """
    from khgrl.common.wire.descriptor import TaskDescriptor

    w, ob, cameras = env.world, env.observation_space, {}
    layout = getattr(env, "cameras", None)
    if layout is not None:  # the observation fields state the state part; the images their shapes
        ob = ob[STATE]
        cameras = {k: tuple(int(d) for d in box.shape) for k, box in layout.images.items()}
    big = 1e30
    reward_bound, obs_bound = value_bounds(task_bounds(env)[0], (w.low, w.high), (ob.low, ob.high))
    return TaskDescriptor(
        name=env.task.name[:64] or "task", spec=(spec or env.task.name)[:200], out_dim=w.out_dim,
        obs_dim=int(ob.shape[0]), obs_low=tuple(np.clip(ob.low.astype(float), -big, big).tolist()),
        obs_high=tuple(np.clip(ob.high.astype(float), -big, big).tolist()), horizon=env.horizon,
        workspace_low=tuple(w.low.tolist()), workspace_high=tuple(w.high.tolist()),
        G=tuple(tuple(r) for r in w.G.tolist()), c=tuple(w.c.tolist()),
        default_scale=tuple(w.default_scale.tolist()), learn_scale=bool(env.task.learn_scale),
        axis_names=tuple(w.view.names), view_axes=tuple(w.view.axes),
        view_third=-1 if w.view.third is None else int(w.view.third),
        shapes=tuple(_shape_dict(s) for s in w.view.shapes), mean=np.asarray(w.model.grid_mean, np.float64),
        demos=np.asarray(w.demos, np.float64), projector=np.asarray(w.model.grid_projector, np.float64),
        reward_bound=reward_bound, obs_bound=obs_bound, cameras=cameras)


def _shape_dict(s) -> dict:
    d = {"kind": s.kind, "name": s.name}
    for k in ("low", "high", "center", "at"):
        if hasattr(s, k):
            d[k] = tuple(float(v) for v in np.asarray(getattr(s, k), dtype=np.float64).reshape(-1))
    if s.kind == "sphere":
        d["radius"] = float(s.radius)
    return d
