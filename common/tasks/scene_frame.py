"""What a viewer needs of an episode's scene (issue 22): the adapted KMP mean, its projector and the via-points of a
:class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` after a reset, as arrays.

A varying-scene task's KMP is refitted through the episode's via-points at every reset (:mod:`khgrl.common.tasks.
adapted`), so the mean and band the demonstrations give (the task descriptor's) are not the episode's. The actor sends
these arrays on the episode's first frame (:func:`frame_scene`, the ``frame`` message's ``scene_*`` fields,
docs/protocol.md) and the renderer draws them (:func:`khgrl.common.tasks.render.frame_from_env`). A fixed-scene task,
or a varying one whose KMP was not adapted (``--no-adapt``, no via-points), has none: its mean is the descriptor's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["SceneArrays", "scene_arrays", "frame_scene", "FRAME_RESERVE"]

log = logging.getLogger("khgrl.actor")

FRAME_RESERVE = 8 * 1024  # bytes of a frame kept for its other fields (6 vectors of <= 64 numbers, obs <= 256)
_warned: set[str] = set()  # what was logged once (per process)


@dataclass(frozen=True)
class SceneArrays:
    """One episode's adapted KMP as a viewer draws it.

    :param mean: (N, O) the adapted mean eta0 over the grid (read-only views of the episode's model).
    :param projector: (N, O, O) its null-space projector (the exploration band is mean +- |projector| L).
    :param via: (V, 1 + O) the via-points: [phase, position...] per row (phase = grid step / (N - 1)).
    """

    mean: np.ndarray
    projector: np.ndarray
    via: np.ndarray


def scene_arrays(env: Any) -> SceneArrays | None:
    """The episode's scene of ``env`` (a KGRLEnv after a reset), or None: a fixed scene, or a varying one whose KMP
    was not adapted (no via-points; the descriptor's mean is then the episode's).

    :param env: a :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` (anything without ``varies`` counts as fixed).
    """
    if not getattr(env, "varies", False) or not getattr(env, "via_points", None):
        return None
    model = env.mapping.model
    mean = np.asarray(model.grid_mean, np.float64)
    n = mean.shape[0]
    via = np.array([[step / max(n - 1, 1), *np.asarray(pos, np.float64).reshape(-1)] for step, pos in env.via_points],
                   dtype=np.float64)
    return SceneArrays(mean=mean, projector=np.asarray(model.grid_projector, np.float64), via=via)


def _warn_once(key: str, msg: str, *args: Any) -> None:
    if key not in _warned:
        _warned.add(key)
        log.warning(msg, *args)


def frame_scene(env: Any, t: int, max_bytes: int) -> dict[str, np.ndarray]:
    """The ``scene_*`` fields of the frame of step ``t`` (only t = 0 has any): the adapted mean, projector and
    via-points, as many as fit a frame of ``max_bytes`` (keeping :data:`FRAME_RESERVE` for the other fields). When
    the projector does not fit (a long grid), only the mean and the via-points go; when the mean does not either,
    only the via-points; each is logged once per process.

    :param env: the actor's KGRLEnv.
    :param t: the step the frame describes.
    :param max_bytes: the frame message's size limit (``Frame.MAX_BYTES``).
    """
    if t != 0:
        return {}
    scene = scene_arrays(env)
    if scene is None:
        return {}
    room = max_bytes - FRAME_RESERVE - scene.via.nbytes
    out = {"scene_via": scene.via}
    if scene.mean.nbytes + scene.projector.nbytes <= room:
        return {**out, "scene_mean": scene.mean, "scene_projector": scene.projector}
    n, o = scene.mean.shape
    if scene.mean.nbytes <= room:
        _warn_once("projector", "frames: the adapted projector (N = %d, O = %d) does not fit a frame of %d bytes; "
                   "episode frames carry the adapted mean and the via-points only (viewers draw the band of the "
                   "demonstrations' projector about it)", n, o, max_bytes)
        return {**out, "scene_mean": scene.mean}
    _warn_once("mean", "frames: the adapted mean (N = %d, O = %d) does not fit a frame of %d bytes; episode frames "
               "carry the via-points only (viewers draw the demonstrations' mean)", n, o, max_bytes)
    return out
