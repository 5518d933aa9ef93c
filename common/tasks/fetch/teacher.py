"""The Fetch pick-and-place task's scripted teacher and its fixed geometry (shared by ``fetch:control``/``moved``,
:mod:`khgrl.common.tasks.fetch.task`, and the varying scenes ``fetch:random``/``obstacle``,
:mod:`khgrl.common.tasks.fetch.scenes`).

A scripted teacher (:func:`teacher_demos`) records M demonstrations of the desired gripper position over N steps,
with the object at ``DEMO_OBJECT``: a wide approach (a random via point), a tight descent, grasp and lift (every
demonstration the same there: the object's place), and a wide carry to the goal. The gripper closes at phase
``GRASP_PHASE``.
"""

from __future__ import annotations

import numpy as np
from khgrl.common.tasks.keyframes import through

__all__ = ["teacher_demos", "through", "HORIZON", "GRASP_PHASE", "DEMO_OBJECT", "GOAL", "START",
           "WORKSPACE", "DEFAULT_SCALE"]

HORIZON = 100
GRASP_PHASE = 0.36  # the gripper closes here
DEMO_OBJECT = np.array([1.30, 0.75, 0.425])  # object centre when the demonstrations were recorded
GOAL = np.array([1.40, 0.95, 0.60])
START = np.array([1.342, 0.749, 0.535])  # Fetch's gripper after reset
WORKSPACE = ((1.05, 0.4, 0.42), (1.55, 1.1, 0.9))  # the table top (z >= 0.42) and the reachable box
# L0, chosen from the model before any run: the band it allows is several cm wide where the demonstrations spread
# (approach, carry) and < 1 mm in y at the grasp, where "moved" needs 12 cm in y (tests/unit/test_fetch_task.py)
DEFAULT_SCALE = 5.0


def teacher_demos(m: int = 6, n: int = HORIZON, seed: int = 0, obj: np.ndarray = DEMO_OBJECT,
                  goal: np.ndarray = GOAL) -> np.ndarray:
    """(m, n, 3) desired gripper positions of a scripted teacher (see the module docstring).

    :param m: demonstrations.
    :param n: steps each.
    :param seed: seed of the variation.
    :param obj: the object's centre.
    :param goal: where the object is carried.
    """
    rng = np.random.default_rng(seed)
    above, lifted = obj + [0.0, 0.0, 0.10], obj + [0.0, 0.0, 0.12]
    demos = np.empty((m, n, 3))
    for k in range(m):
        via1 = (START + above) / 2 + [rng.uniform(-0.06, 0.06), rng.uniform(-0.08, 0.08), rng.uniform(0.0, 0.06)]
        via2 = (lifted + goal) / 2 + [rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), rng.uniform(0.0, 0.08)]
        keys = [(0.0, START), (0.12, via1), (0.24, above), (0.32, obj), (0.42, obj), (0.52, lifted),
                (0.70, via2), (0.88, goal), (1.0, goal)]
        demos[k] = through(keys, n)
    return demos


