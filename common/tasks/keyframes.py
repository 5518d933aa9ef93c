"""Scripted teachers' paths: positions through (phase, point) keyframes, minimum-jerk between consecutive ones
(the Fetch and Panda teachers, :mod:`khgrl.common.tasks.fetch.teacher`, :mod:`khgrl.common.tasks.panda.task`)."""

from __future__ import annotations

import numpy as np

__all__ = ["min_jerk", "through"]


def min_jerk(u: np.ndarray) -> np.ndarray:
    """The minimum-jerk profile 10 u^3 - 15 u^4 + 6 u^5 on u in [0, 1]."""
    return 10 * u**3 - 15 * u**4 + 6 * u**5


def through(keys: list[tuple[float, np.ndarray]], n: int) -> np.ndarray:
    """(n, O) positions at n phases in [0, 1] through (phase, point) keyframes, minimum-jerk between consecutive ones.

    :param keys: (phase, point (O,)) in increasing phase, the first at 0 and the last at 1.
    :param n: the number of phases.
    """
    s = np.linspace(0.0, 1.0, n)
    out = np.empty((n, len(keys[0][1])))
    for (s0, p0), (s1, p1) in zip(keys[:-1], keys[1:]):
        sel = (s >= s0) & (s <= s1)
        out[sel] = p0 + min_jerk((s[sel] - s0) / (s1 - s0))[:, None] * (np.asarray(p1) - np.asarray(p0))
    return out
