"""One episode's scene: the placement read from the first observation and the KMP adapted to its via-points.

:func:`episode_scene` is what :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` calls at every reset of a task with a
:class:`~khgrl.common.tasks.scene.Scene`. A task's ``describe`` and ``via_points`` are the user's code: whatever they
get wrong is one :class:`~khgrl.common.tasks.api.TaskError` naming the task and the function.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from khgrl.common.kmp.adapt import adapt_model, snap_via_points
from khgrl.common.kmp.lcnskmp import LCNSKMP
from khgrl.common.tasks.api import TaskError
from khgrl.common.tasks.scene import MAX_PLACEMENT, MAX_VIA_POINTS

__all__ = ["EpisodeScene", "episode_scene", "read_placement", "WORKSPACE_TOL"]

WORKSPACE_TOL = 1e-9  # a via-point on the workspace's edge, give or take rounding, is inside


@dataclass(frozen=True)
class EpisodeScene:
    """The scene of one episode.

    :param placement: ``Scene.describe(obs)``: name -> value.
    :param via_points: (grid step, position (O,)) of the via-points the model was adapted to (empty: not adapted).
    :param model: the LC-NS-KMP the episode is driven with (the task's own when not adapted).
    :param key: what the model was adapted to (a cache key: the next episode with the same via-points reuses it).
    """

    placement: dict[str, float]
    via_points: list[tuple[int, np.ndarray]]
    model: LCNSKMP
    key: tuple = ()


def read_placement(task: Any, obs: np.ndarray) -> dict[str, float]:
    """The placement of a scene, ``task.scene.describe(obs)``, checked: at most 16 finite numbers by name.

    :param task: a task with a scene.
    :param obs: the first observation of the task's environment.
    :raises TaskError: describe raised or gave something else.
    """
    try:
        got = task.scene.describe(obs)
        placement = {str(k): float(v) for k, v in dict(got).items()}
    except Exception as exc:  # noqa: BLE001 - the user's function
        raise TaskError(f"task {task.name!r}: Scene.describe raised {type(exc).__name__}: {exc} (it must map the "
                        f"first observation to {{name: number}})") from None
    if len(placement) > MAX_PLACEMENT or not all(np.isfinite(v) for v in placement.values()):
        raise TaskError(f"task {task.name!r}: Scene.describe must give at most {MAX_PLACEMENT} finite numbers, got "
                        f"{placement}")
    return placement


def episode_scene(world: Any, obs: np.ndarray, *, adapt: bool = True, cache: EpisodeScene | None = None
                  ) -> EpisodeScene:
    """The placement and the episode's LC-NS-KMP for the first observation ``obs`` of an episode.

    :param world: the task's :class:`~khgrl.common.tasks.world.TaskWorld` (its model is the demonstrations' KMP).
    :param obs: the first observation of the task's environment.
    :param adapt: refit through ``task.scene.via_points(obs)`` (False: the demonstrations' model).
    :param cache: the previous episode's scene: its model is reused when the via-points are the same.
    :raises TaskError: ``describe`` or ``via_points`` raised or gave something unusable.
    """
    task = world.task
    placement = read_placement(task, obs)
    if not adapt or task.scene.via_points is None:
        return EpisodeScene(placement, [], world.model)
    try:
        via = list(task.scene.via_points(obs))
        snapped = snap_via_points(world.model, via)
    except Exception as exc:  # noqa: BLE001 - the user's function, or a via-point it got wrong
        raise TaskError(f"task {task.name!r}: Scene.via_points: {type(exc).__name__}: {exc}") from None
    if len(snapped) > MAX_VIA_POINTS:
        raise TaskError(f"task {task.name!r}: Scene.via_points gave {len(snapped)} via-points (at most "
                        f"{MAX_VIA_POINTS})")
    _check_in_workspace(world, snapped)
    key = tuple((s.step, *s.position.tolist(), float(s.sigma[0, 0])) for s in snapped)
    if cache is not None and cache.key == key and cache.via_points:
        model = cache.model
    else:
        try:
            model = adapt_model(world.model, via)
        except Exception as exc:  # noqa: BLE001 - e.g. constraints the via-points make infeasible
            raise TaskError(f"task {task.name!r}: adapting the KMP to the via-points failed: "
                            f"{type(exc).__name__}: {exc}") from None
    return EpisodeScene(placement, [(s.step, s.position) for s in snapped], model, key)


def _check_in_workspace(world: Any, snapped: list) -> None:
    """A via-point the robot may not reach is the task's mistake: the KMP mean would be bent to a place every
    command is clipped away from.

    :raises TaskError: a via-point outside the workspace box (by more than ``WORKSPACE_TOL``).
    """
    for k, s in enumerate(snapped):
        if np.any(s.position < world.low - WORKSPACE_TOL) or np.any(s.position > world.high + WORKSPACE_TOL):
            raise TaskError(f"task {world.task.name!r}: Scene.via_points: via-point {k} at "
                            f"{np.round(s.position, 6).tolist()} lies outside the workspace box "
                            f"{world.low.tolist()}..{world.high.tolist()}")
