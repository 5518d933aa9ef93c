"""Pick and place with gymnasium-robotics' Fetch arm as a task of the task API: ``--task fetch:control`` and
``--task fetch:moved`` (issue 12), and the scenes that change every episode, ``--task fetch:random`` and
``--task fetch:obstacle`` (issue 22, :mod:`khgrl.common.tasks.fetch.scenes`).

A scripted teacher (:func:`teacher_demos`) records M demonstrations of the desired gripper position over N steps
in the same environment, with the object at ``DEMO_OBJECT``: a wide approach (a random via point), a tight
descent, grasp and lift (every demonstration the same there: the object's place), and a wide carry to the goal.
The gripper closes at phase ``GRASP_PHASE`` (:class:`~khgrl.common.tasks.fetch.arm.GripperSchedule`).

Scenarios: ``control`` places the object where the demonstrations grasped it; ``moved`` places it ``MOVE`` away,
where the demonstrations agree (the paper's "the environment changed after the demonstrations"). ``random`` and
``obstacle`` draw the scene at every reset (:mod:`khgrl.common.tasks.fetch.scenes`).
"""

from __future__ import annotations

import numpy as np
from khgrl.common.tasks.api import Cuboid, Point, Sphere, Task, View
from khgrl.common.tasks.fetch.arm import OBS_BOUND, REWARD_BOUND, FetchPosition, GripperSchedule
from khgrl.common.tasks.fetch.scenes import SCENE_SCENARIOS, make_scene_task
from khgrl.common.tasks.fetch.teacher import (
    DEFAULT_SCALE,
    DEMO_OBJECT,
    GOAL,
    GRASP_PHASE,
    HORIZON,
    WORKSPACE,
    teacher_demos,
)

__all__ = ["make_task", "teacher_demos", "DEMO_OBJECT", "GOAL", "MOVE", "GRASP_PHASE", "SCENARIOS"]

MOVE = np.array([0.0, -0.12, 0.0])  # "moved": the object is here relative to DEMO_OBJECT
SCENARIOS = {"control": np.zeros(3), "moved": MOVE}


class FetchGuide:
    """The scripted human: while the KMP mean is at the demonstrations' grasp (near ``DEMO_OBJECT``, low), it
    drags the gripper by ``offset`` to where the object really is; elsewhere it lets go."""

    def __init__(self, offset: np.ndarray) -> None:
        self.offset = np.asarray(offset, np.float64)

    def __call__(self, mean: np.ndarray) -> np.ndarray | None:
        near = np.linalg.norm(mean[:2] - DEMO_OBJECT[:2]) < 0.03 and mean[2] < DEMO_OBJECT[2] + 0.11
        return mean + self.offset if near and np.any(self.offset) else None


def make_task(scenario: str = "moved", *, horizon: int = HORIZON, seed: int = 0) -> Task:
    """Fetch pick and place for ``scenario`` ("control", "moved", "random" or "obstacle").

    :param scenario: where the object is at training time.
    :param horizon: N, steps per episode.
    :param seed: seed of the teacher's demonstrations.
    """
    if scenario in SCENE_SCENARIOS:
        return make_scene_task(scenario, horizon=horizon, seed=seed)
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown fetch scenario {scenario!r}; choose one of {sorted(SCENARIOS) + SCENE_SCENARIOS}")
    obj = DEMO_OBJECT + SCENARIOS[scenario]
    sched = GripperSchedule(close_at=GRASP_PHASE, open_at=1.1)
    return Task(
        name=f"fetch-{scenario}",
        make_env=lambda s: FetchPosition(horizon=horizon, workspace=WORKSPACE, gripper=sched,
                                         object_xy=tuple(obj[:2]), goal=tuple(GOAL)),
        demos=teacher_demos(n=horizon, seed=seed), workspace=WORKSPACE, default_scale=DEFAULT_SCALE, learn_scale=True,
        action_cost=10.0, position=lambda obs: obs[:3], scripted_human=FetchGuide(SCENARIOS[scenario]),
        reward_bound=REWARD_BOUND, obs_bound=OBS_BOUND,
        view=View(axes=(0, 1), third=2, names=("x", "y", "z"),
                  shapes=(Sphere("object", tuple(obj), 0.025), Point("demo object", tuple(DEMO_OBJECT)),
                          Point("goal", tuple(GOAL)), Cuboid("table", (1.05, 0.4, 0.40), (1.55, 1.1, 0.42)))))
