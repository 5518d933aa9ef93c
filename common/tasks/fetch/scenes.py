"""Fetch scenes that change every episode (issue 22): ``--task fetch:random`` and ``--task fetch:obstacle``.

``fetch:random``: the object is placed uniformly at every reset in x in [1.22, 1.42], y in [0.60, 0.90] (not within
5 cm of the gripper's start; :mod:`khgrl.common.tasks.fetch.scene_env`), far wider than the demonstrations' band at
the grasp (< 2.4 mm). The goal is fixed at ``GOAL``, so that the variation is the object alone. The demonstrations
are the scripted teacher's at ``DEMO_OBJECT`` (:func:`~khgrl.common.tasks.fetch.teacher.teacher_demos`).

* ``Scene.describe(obs)``: the object's (x, y) from the first observation (obs[3:6] is the object's position).
* ``Scene.via_points(obs)``: the grasp, the part of the teacher's path that is fixed relative to the object
  (above it at 0.24, down, grasp: the gripper closes at 0.36), re-targeted to the observed object: a via-point at
  each of the 16 grid steps (N = 100) from phase ``VIA_PHASES[0]`` to ``VIA_PHASES[1]``, precision ``VIA_PRECISION``
  (the mean passes within 0.4 mm of each under the rule "a via-point replaces the reference point at its grid
  step"). Every step of the grasp is pinned: where one is not, the KMP mean returns to the demonstrations' grasp
  within a step or two (their covariance there is ~2e-6 m^2 in x, y: two via-points at 0.32 and 0.42 leave the mean
  10-15 cm from the object at the steps between them). They start above the object, so that the mean's move from
  the demonstrations' path to the object is made 10 cm above the table (starting them at 0.30, mid-descent, knocks
  the object over in 5 of 8 scenes); after 0.40 the mean returns to the demonstrations' lift and carry with the
  object held.
* The scripted human (:class:`GraspGuide`): at the grasp phases, while the gripper is more than ``GRASP_NEAR`` from
  the observed object in (x, y), it drags P_h to the object's (x, y) at the mean's height; else it lets go.

``fetch:obstacle`` (the variation a via-point from the observation does not express, issue 22 point 5):
``fetch:random`` plus a 12 x 5 x 23 cm block standing on the table (top z = 0.63) at a random place on the
demonstrations' carry path (:func:`~khgrl.common.tasks.fetch.scene_env.draw_obstacle_scene`), a real MuJoCo body
the arm and the carried object collide with; its centre is appended to the observation (obs[28:31]). The KMP is
adapted at the grasp as in ``fetch:random`` but not around the obstacle: the carry that the adapted mean follows
runs through it (tests/unit/test_fetch_scenes.py). The scripted human (:class:`ObstacleGuide`) does the grasp's
work as above and lifts P_h over the obstacle (``CLEAR`` above its top) while the mean is within ``NEAR`` of it in
(x, y) after the grasp (:func:`over_obstacle`).
"""

from __future__ import annotations

import numpy as np
from khgrl.common.tasks.api import Cuboid, Point, Scene, Task, ViaPoint, View
from khgrl.common.tasks.fetch.arm import OBS_BOUND, REWARD_BOUND, GripperSchedule
from khgrl.common.tasks.fetch.scene_env import (
    OBJECT_REGION,
    OBSTACLE_TOP,
    FetchObstacle,
    FetchRandomObject,
    box_gap,
)
from khgrl.common.tasks.fetch.teacher import (
    DEFAULT_SCALE,
    DEMO_OBJECT,
    GOAL,
    GRASP_PHASE,
    HORIZON,
    WORKSPACE,
    teacher_demos,
)

__all__ = ["make_scene_task", "SCENE_SCENARIOS", "GraspGuide", "ObstacleGuide", "grasp_path", "describe_object",
           "describe_obstacle", "grasp_via_points", "VIA_PHASES", "VIA_PRECISION"]

SCENE_SCENARIOS = ["random", "obstacle"]
VIA_PHASES = (0.24, 0.40)  # the grasp: from above the object (0.24) through the grasp (0.36)
VIA_PRECISION = 1e8  # 1 / variance (m^-2): sigma = 0.1 mm
GRASP_NEAR = 0.01  # metres (x, y): the gripper is "at the object"
NEAR = 0.07  # metres (x, y) from the obstacle's footprint, on the way to it: the human lifts over it
LEAVE = 0.035  # metres (x, y) from the footprint after it: the human lets the mean come down
CLEAR = 0.07  # metres: how far above the obstacle's top the human lifts the gripper (object half 2.5 cm + 4.5 cm)
AFTER_GRASP = 0.45  # the obstacle human acts only from here on (the object is held)


def grasp_path(obj: np.ndarray, n: int = HORIZON) -> np.ndarray:
    """(n, 3) the teacher's path re-targeted to the object at ``obj``; it does not depend on the teacher's random
    via points between phases 0.24 and 0.52 (above the object, down, grasp, lift).

    :param obj: the object's centre.
    :param n: steps.
    """
    return teacher_demos(m=1, n=n, obj=np.asarray(obj, np.float64))[0]


def grasp_steps(n: int = HORIZON) -> np.ndarray:
    """The grid steps of the grasp (phases in ``VIA_PHASES``), at most 16."""
    steps = np.arange(int(np.ceil(VIA_PHASES[0] * (n - 1) - 1e-9)), int(np.floor(VIA_PHASES[1] * (n - 1))) + 1)
    return steps[:16]


def describe_object(obs: np.ndarray) -> dict[str, float]:
    """The placement: the object's (x, y) in the first observation.

    :param obs: the environment's observation.
    """
    return {"object_x": float(obs[3]), "object_y": float(obs[4])}


def describe_obstacle(obs: np.ndarray) -> dict[str, float]:
    """The placement: the object's and the obstacle's (x, y) in the first observation.

    :param obs: the environment's observation.
    """
    return {**describe_object(obs), "obstacle_x": float(obs[28]), "obstacle_y": float(obs[29])}


def grasp_via_points(obs: np.ndarray, n: int = HORIZON) -> list[ViaPoint]:
    """The via-points of the grasp at the observed object (see the module docstring).

    :param obs: the episode's first observation.
    :param n: the KMP grid's length.
    """
    path = grasp_path(np.asarray(obs[3:6], np.float64), n)
    return [ViaPoint(phase=float(t / (n - 1)), position=path[t].copy(), precision=VIA_PRECISION)
            for t in grasp_steps(n)]


class GraspGuide:
    """The scripted human of ``fetch:random``: at the grasp phases, if the gripper is more than ``GRASP_NEAR`` from
    the observed object in (x, y), P_h is the object's (x, y) at the KMP mean's height; else None (also before the
    first observation)."""

    def __call__(self, mean: np.ndarray, *, phase: float | None = None, position: np.ndarray | None = None,
                 obs: np.ndarray | None = None) -> np.ndarray | None:
        if obs is None or phase is None or not VIA_PHASES[0] <= phase <= VIA_PHASES[1]:
            return None
        gripper = mean if position is None else np.asarray(position, np.float64)
        obj = np.asarray(obs[3:6], np.float64)
        if np.linalg.norm(gripper[:2] - obj[:2]) <= GRASP_NEAR:
            return None
        return np.array([obj[0], obj[1], mean[2]])


def over_obstacle(mean: np.ndarray, obstacle: np.ndarray, goal: np.ndarray = GOAL) -> np.ndarray | None:
    """P_h that lifts ``mean`` to ``CLEAR`` above the obstacle centred at ``obstacle`` while its (x, y) is within
    ``NEAR`` of the obstacle's footprint on the way to it (farther from the goal than the obstacle) or within
    ``LEAVE`` after it (the carried object's half and a centimetre: the goal is ``GOAL_CLEARANCE`` from the
    footprint, so the mean comes down beside it); else None.

    :param mean: the KMP mean (3,).
    :param obstacle: the obstacle's centre (3,).
    :param goal: the goal (3,).
    """
    approaching = np.linalg.norm(mean[:2] - goal[:2]) > np.linalg.norm(obstacle[:2] - goal[:2])
    if box_gap(mean, obstacle) > (NEAR if approaching else LEAVE) or mean[2] >= OBSTACLE_TOP + CLEAR:
        return None
    return np.array([mean[0], mean[1], OBSTACLE_TOP + CLEAR])


class ObstacleGuide(GraspGuide):
    """The scripted human of ``fetch:obstacle``: the grasp as :class:`GraspGuide`; after it (phase >=
    ``AFTER_GRASP``) it lifts P_h over the obstacle read from the observation (:func:`over_obstacle`)."""

    def __call__(self, mean: np.ndarray, *, phase: float | None = None, position: np.ndarray | None = None,
                 obs: np.ndarray | None = None) -> np.ndarray | None:
        p_h = super().__call__(mean, phase=phase, position=position, obs=obs)
        if p_h is not None or obs is None or phase is None or phase < AFTER_GRASP:
            return p_h
        return over_obstacle(np.asarray(mean, np.float64), np.asarray(obs[28:31], np.float64),
                             np.asarray(obs[25:28], np.float64))


def _region_text(obstacle: bool) -> str:
    (x0, y0), (x1, y1) = OBJECT_REGION
    text = f"object x in [{x0}, {x1}], y in [{y0}, {y1}] (uniform, >= 5 cm from the start); goal fixed at "
    text += str(GOAL.tolist())
    if obstacle:
        text += ("; a 12 x 5 cm block (top z = 0.63) at a uniform place on the demonstrations' carry path (phases "
                 "0.63-0.75, +-2 cm across), the object redrawn until clear of it (then y <= 0.85, 98 % below 0.80)")
    return text


def make_scene_task(scenario: str = "random", *, horizon: int = HORIZON, seed: int = 0) -> Task:
    """``fetch:random`` or ``fetch:obstacle`` (see the module docstring).

    :param scenario: "random" or "obstacle".
    :param horizon: N, steps per episode.
    :param seed: seed of the teacher's demonstrations (at ``DEMO_OBJECT``).
    """
    if scenario not in SCENE_SCENARIOS:
        raise ValueError(f"unknown fetch scene {scenario!r}; choose one of {SCENE_SCENARIOS}")
    obstacle = scenario == "obstacle"
    sched = GripperSchedule(close_at=GRASP_PHASE, open_at=1.1)
    cls = FetchObstacle if obstacle else FetchRandomObject
    (x0, y0), (x1, y1) = OBJECT_REGION
    shapes = (Cuboid("object region", (x0, y0, 0.40), (x1, y1, 0.45)), Point("demo object", tuple(DEMO_OBJECT)),
              Point("goal", tuple(GOAL)), Cuboid("table", (1.05, 0.4, 0.40), (1.55, 1.1, 0.42)))
    return Task(
        name=f"fetch-{scenario}",
        make_env=lambda s: cls(horizon=horizon, workspace=WORKSPACE, gripper=sched, goal=tuple(GOAL)),
        demos=teacher_demos(n=horizon, seed=seed), workspace=WORKSPACE, default_scale=DEFAULT_SCALE, learn_scale=True,
        action_cost=10.0, position=lambda obs: obs[:3], scripted_human=ObstacleGuide() if obstacle else GraspGuide(),
        reward_bound=REWARD_BOUND, obs_bound=OBS_BOUND,
        view=View(axes=(0, 1), third=2, names=("x", "y", "z"), shapes=shapes),
        scene=Scene(region=_region_text(obstacle), describe=describe_obstacle if obstacle else describe_object,
                    via_points=lambda obs: grasp_via_points(obs, horizon)))
