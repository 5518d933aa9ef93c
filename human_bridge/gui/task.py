"""The GUI's task: a :class:`~khgrl.common.wire.descriptor.TaskDescriptor` built locally (offline screenshots, ``khgrl
demos
record``, tests), and the exploration band from the descriptor's projector.

The band an actor's L allows is eta0 +- |N| L per grid point (:meth:`khgrl.common.kmp.mapping.KGRLMapping.band`); the
descriptor carries N, the KMP's null-space projector on the grid, so the GUI never needs the task's code.
"""

from __future__ import annotations

import numpy as np
from khgrl.common.wire.descriptor import TaskDescriptor

__all__ = ["local_descriptor", "local_world", "band"]


def local_world(spec: str, demos=None):
    """The :class:`~khgrl.common.tasks.world.TaskWorld` of ``spec`` built here (``demos``: a file or (M, N, O) array
    replacing the task's demonstrations).

    :raises khgrl.common.tasks.api.TaskError: naming what is wrong with the task.
    """
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.world import build_task_world

    task = load_task(spec)
    if demos is not None:
        task = task.with_demos(demos)
    return build_task_world(task)


def local_descriptor(spec: str, demos=None, world=None) -> TaskDescriptor:
    """The descriptor an actor of ``spec`` would announce, built here (fits the task's KMP unless ``world``).

    :param spec: ``passage:high_cov`` or ``package.module:callable``.
    :param demos: a demonstration file (or array) replacing the task's.
    :param world: an already built world of that task.
    """
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    env = KGRLEnv(world=world if world is not None else local_world(spec, demos))
    try:
        return env.descriptor(spec)
    finally:
        env.close()


def band(d: TaskDescriptor, L: np.ndarray, mean: np.ndarray | None = None, projector: np.ndarray | None = None
         ) -> np.ndarray:
    """(N, 2, O) [low, high] of the exploration band under L ((N, O) or (O,)).

    :param d: the run's task.
    :param L: the exploration scale on the grid, or one value per output.
    :param mean: (N, O) the episode's adapted mean (default: the descriptor's, the demonstrations').
    :param projector: (N, O, O) the episode's adapted projector (default: the descriptor's).
    """
    mean = np.asarray(d.mean if mean is None else mean, dtype=np.float64)
    proj = np.asarray(d.projector if projector is None else projector, dtype=np.float64)
    half = np.einsum("nij,nj->ni", np.abs(proj), np.broadcast_to(np.asarray(L, np.float64), mean.shape))
    return np.stack([mean - half, mean + half], axis=1)
