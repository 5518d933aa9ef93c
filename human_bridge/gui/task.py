"""The GUI's task: a :class:`~common.descriptor.TaskDescriptor` built locally (offline screenshots, ``khgrl demos
record``, tests), and the exploration band's projector, which the descriptor does not carry.

The band an actor's L allows is eta0 +- |N| L per grid point (:meth:`common.kgrl.KGRLMapping.band`); N, the
KMP's null-space projector, is not part of the descriptor, so :func:`band_projector` rebuilds the task's world
here from the descriptor's spec and demonstrations and uses it only if its KMP mean is the descriptor's. When the
task cannot be built here (its code is not importable on this machine) the GUI draws no band.
"""

from __future__ import annotations

import logging

import numpy as np

from common.descriptor import TaskDescriptor

__all__ = ["local_descriptor", "local_world", "band_projector", "band"]

log = logging.getLogger("khgrl.human.gui")

_PROJECTORS: dict[str, np.ndarray | None] = {}


def local_world(spec: str, demos=None):
    """The :class:`~common.task_world.TaskWorld` of ``spec`` built here (``demos``: a file or (M, N, O) array
    replacing the task's demonstrations).

    :raises common.task.TaskError: naming what is wrong with the task.
    """
    from common.task import load_task
    from common.task_world import build_task_world

    task = load_task(spec)
    if demos is not None:
        task = task.with_demos(demos)
    return build_task_world(task)


def local_descriptor(spec: str, demos=None, world=None) -> TaskDescriptor:
    """The descriptor an actor of ``spec`` would announce, built here (fits the task's KMP unless ``world``; its
    projector is kept for :func:`band_projector`).

    :param spec: ``passage:high_cov`` or ``package.module:callable``.
    :param demos: a demonstration file (or array) replacing the task's.
    :param world: an already built world of that task.
    """
    from common.kgrl_env import KGRLEnv

    env = KGRLEnv(world=world if world is not None else local_world(spec, demos))
    try:
        d = env.descriptor(spec)
    finally:
        env.close()
    _PROJECTORS.setdefault(d.digest, np.abs(np.asarray(env.world.model.grid_projector, dtype=np.float64)))
    return d


def band_projector(d: TaskDescriptor) -> np.ndarray | None:
    """|N| (N, O, O) of the task's KMP on its grid, rebuilt here once per task (None: not possible here)."""
    key = d.digest
    if key not in _PROJECTORS:
        _PROJECTORS[key] = None
        try:
            w = local_world(d.spec, np.asarray(d.demos))
            mean = np.asarray(w.model.grid_mean)
            if mean.shape == np.shape(d.mean) and np.allclose(mean, d.mean, atol=1e-6, rtol=1e-6):
                _PROJECTORS[key] = np.abs(np.asarray(w.model.grid_projector, dtype=np.float64))
            else:
                log.warning("task %s: the KMP rebuilt here differs from the actor's: no exploration band", d.name)
        except Exception as exc:  # noqa: BLE001 - a task whose code is not here: draw without the band
            log.warning("task %s (%s) cannot be built here (%s: %s): no exploration band", d.name, d.spec,
                        type(exc).__name__, exc)
    return _PROJECTORS[key]


def band(d: TaskDescriptor, L: np.ndarray) -> np.ndarray | None:
    """(N, 2, O) [low, high] of the exploration band under L ((N, O) or (O,)), or None without a projector."""
    proj = band_projector(d)
    if proj is None:
        return None
    mean = np.asarray(d.mean, dtype=np.float64)
    half = np.einsum("nij,nj->ni", proj, np.broadcast_to(np.asarray(L, np.float64), mean.shape))
    return np.stack([mean - half, mean + half], axis=1)
