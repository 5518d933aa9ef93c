"""Scenes that change every episode: the task API's :class:`Scene` and :class:`ViaPoint` (issue 22).

A task whose scene varies (an object placed at random at each reset) declares a :class:`Scene`:

* its environment's ``reset(seed=...)`` draws the placement from the seed, in the range ``Scene.region`` states;
  the actor resets episode ``e`` of a run with seed ``S`` with :func:`scene_seed` ``(S, e)``, and
  ``khgrl eval --scenes K`` resets scene ``k`` with ``scene_seed(S, k, stream="eval")`` -- another stream, so that
  evaluation scenes are not the training ones;
* ``describe(obs)`` reads the placement from the episode's first observation (the per-scene CSV's columns);
* ``via_points(obs)`` (optional) says how the scene adapts the KMP: points (phase, position, precision) the
  episode's mean must pass through, e.g. the grasp at the object's observed position. The actor refits the
  LC-NS-KMP with them at every reset (:func:`khgrl.common.kmp.adapt.adapt_model`, the KMP paper's via-point
  adaptation: Huang et al., "Kernelized movement primitives", IJRR 2019, "trajectory modulation": desired points
  added to the reference database).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

__all__ = ["Scene", "ViaPoint", "scene_seed", "SCENE_STREAMS", "MAX_VIA_POINTS", "MAX_PLACEMENT"]

MAX_VIA_POINTS = 16  # via-points per episode a task may give
MAX_PLACEMENT = 16  # entries of a placement (describe(obs))
SCENE_STREAMS = {"train": 0, "eval": 1}
DEFAULT_PRECISION = 1e6  # 1 / variance of a via-point (metres^-2 for a position task: sigma = 1 mm)


@dataclass(frozen=True)
class ViaPoint:
    """A point the adapted KMP mean passes through: the desired point (s_bar, mu_bar, Sigma_bar) that the KMP paper
    adds to the reference database (Huang et al. 2019, trajectory modulation with via-points and end-points).

    :param phase: s_bar in [0, 1]; the actor snaps it to the nearest step of the KMP grid (the only phases it
        visits), where the point replaces the reference point (the paper's rule for a coinciding input).
    :param position: mu_bar, the position (O,) in command coordinates.
    :param precision: 1 / variance: Sigma_bar = I / precision. Larger pins the mean harder and narrows the band
        there (the projector follows Sigma, math.md §4).
    """

    phase: float
    position: Any
    precision: float = DEFAULT_PRECISION


@dataclass(frozen=True)
class Scene:
    """How a task's scene varies (see the module docstring).

    :param region: the stated range of the placement, in words (printed by ``khgrl eval --scenes`` and the docs),
        e.g. "object x in [1.22, 1.42], y in [0.55, 0.95] (uniform)".
    :param describe: ``describe(obs) -> {name: value}``: the placement, from the episode's first observation of
        the task's environment (at most 16 finite numbers).
    :param via_points: ``via_points(obs) -> [ViaPoint, ...]``: how the scene adapts the KMP (None: it does not).
    """

    region: str
    describe: Callable[[np.ndarray], dict[str, float]]
    via_points: Callable[[np.ndarray], Sequence[ViaPoint]] | None = None


def scene_seed(seed: int, index: int, *, stream: str = "train") -> int:
    """The reset seed of scene ``index`` (a training episode, 1-based, or an evaluation scene) of a run seeded
    ``seed``: independent streams per (seed, stream), in [0, 2^31).

    :param seed: the run's (actor's) seed.
    :param index: the episode or scene number.
    :param stream: "train" or "eval".
    """
    if stream not in SCENE_STREAMS:
        raise ValueError(f"stream must be one of {tuple(SCENE_STREAMS)}, got {stream!r}")
    ss = np.random.SeedSequence([int(seed) % 2**63, SCENE_STREAMS[stream], int(index) % 2**63])
    return int(ss.generate_state(1, np.uint32)[0] >> 1)
