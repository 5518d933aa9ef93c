"""LeRobot's gym-hil Panda pick-cube as a task of the task API: ``--task panda:pick``.

The environment (:class:`~khgrl.common.tasks.panda.arm.PandaPosition`) places the cube uniformly in gym-hil's own
sampling region (x in [0.3, 0.5], y in [-0.15, 0.15] m) at every reset, from the reset's seed: the scene changes
every episode (:class:`~khgrl.common.tasks.scene.Scene`). Success is gym-hil's: the cube more than 10 cm above
where it started (its sparse reward 1, ``info["succeed"]``; it also ends the episode).

A scripted teacher (:func:`teacher_demos`) records M demonstrations of the desired gripper position over N steps,
each with the cube at another place in the region (:func:`demo_cubes`, seeded; a teacher shows the task where the
cube happens to be): a wide approach (a random via point), a descent to above the cube and onto it, a hold while
the gripper closes (at phase ``GRASP_PHASE``), and a lift. Where the demonstrations grasp thus varies across them,
so the KMP's reference covariance there is the spread of the cube's places, and via-points (:func:`via_points`)
with a far smaller covariance win: 16 points of the teacher's own plan for the observed cube, from above it
(phase 0.30) to the end of the lift (0.80), every second grid step at N = 60. The KMP's length scale is 0.05
(3 grid steps; the default 0.02 is 1.2 steps), so that the mean follows the via-points between them too. Measured
(the adapted mean alone, 8 scenes): with the default length scale it swings back toward the demonstrations'
average grasp at the steps between via-points (4-6 cm during the hold); with only the four keyframes as via-points
it lifted the cube in 1 of 8 scenes; as chosen, in 8 of 8; with all demonstrations at one place (the reference
covariance ~0 at the grasp), the mean is pinned there between via-points and lifted none.

The scripted human (:class:`PandaGuide`): during the grasp part of the task (descent, hold, lift), while the KMP
mean is more than 1 cm (in x, y) from the cube it sees, it drags P_h over the cube at the mean's height;
elsewhere, or when the mean is already there, it lets go.

``panda:pick-pixels`` (issue 37): the same task -- demonstrations, KMP, scene, via-points, scripted human, bounds --
whose environment observes gym-hil's cameras (:class:`~khgrl.common.tasks.panda.pixels.PandaPixels`): the policy
sees ``front`` and ``wrist`` (128 x 128 x 3 uint8) and the state vector ``agent_pos`` (the robot's position is read
from it); the scene and the scripted human read the cube's true position from ``environment_state``, which the
policy does not see.

``panda:pick-camera``: ``panda:pick`` whose scene (placement, via-points) is what gym-hil's front camera sees
(:class:`~khgrl.common.tasks.panda.seen.PandaSeen`); its observations are ``panda:pick``'s after the reset, so a
policy trained on ``panda:pick`` runs on it unchanged (``khgrl eval RUN --task panda:pick-camera``).
``panda:pick-pixels-camera``: both, ``panda:pick-pixels`` whose scene is located in its own first ``front`` frame.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from khgrl.common.kmp.fit import KMPConfig
from khgrl.common.tasks.api import Cuboid, Point, Task, View
from khgrl.common.tasks.fetch.arm import GripperSchedule
from khgrl.common.tasks.keyframes import through
from khgrl.common.tasks.panda.arm import BOUNDS, REGION, PandaPosition
from khgrl.common.tasks.panda.pixels import CAMERAS, STATE_KEY, PandaPixels, cube_of, tcp_of
from khgrl.common.tasks.panda.seen import PandaSeen
from khgrl.common.tasks.scene import Scene, ViaPoint

__all__ = ["make_task", "teacher_demos", "demo_cubes", "teacher_plan", "via_points", "describe", "PandaGuide",
           "DEMO_CUBE", "GRASP_PHASE", "HORIZON", "SCENARIOS", "keyframes", "VIA_PHASES", "KMP"]

HORIZON = 60  # 6 s at gym-hil's 10 Hz
START = np.array([0.490, 0.0, 0.078])  # the pinch site after gym-hil's reset (its home joint angles)
DEMO_CUBE = np.array([0.40, 0.0, 0.02])  # the region's centre (the human's "demo cube" mark in the views)
GRASP_Z = 0.02  # the pinch site at the cube's centre height (the cube is 4 cm wide, centre 2 cm above the table)
ABOVE, LIFT = 0.08, 0.16  # heights above the grasp: the descent starts here; the lift ends here (success at 10 cm)
PHASES = {"above": 0.30, "grasp": 0.42, "hold": 0.55, "lift": 0.80}
GRASP_PHASE = 0.46  # the gripper closes here (after the pinch site reaches the cube, before the lift starts)
NEAR = 0.01  # the scripted human lets go when the mean is this close (x, y) to the cube
SCENARIOS = ("pick", "pick-pixels", "pick-camera", "pick-pixels-camera")  # pixels.py: observes gym-hil's
# cameras; seen.py: the scene from the front camera
VIA_PHASES = np.linspace(PHASES["above"], PHASES["lift"], 16)  # where the via-points are (16: the most allowed)
KMP = KMPConfig(length_scale=0.05)  # see the module docstring
# L0: the fetch task's choice (same units: metres, a band of a few cm where the demonstrations spread); not tuned
DEFAULT_SCALE = 5.0


def keyframes(cube: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """(phase, position) of the grasp part of the task for a cube at ``cube``: above it, at it, held, lifted.

    :param cube: the cube's centre (3,).
    """
    at = np.array([cube[0], cube[1], GRASP_Z])
    return [(PHASES["above"], at + [0, 0, ABOVE]), (PHASES["grasp"], at), (PHASES["hold"], at),
            (PHASES["lift"], at + [0, 0, LIFT])]


def demo_cubes(m: int = 6, seed: int = 0) -> np.ndarray:
    """(m, 3) the cube's centre in each of the teacher's demonstrations: uniform in the region, on the table.

    :param m: demonstrations.
    :param seed: seed of the places.
    """
    rng = np.random.default_rng([seed, 1])
    (x0, y0), (x1, y1) = REGION
    return np.array([[rng.uniform(x0, x1), rng.uniform(y0, y1), GRASP_Z] for _ in range(m)])


def teacher_plan(cube: np.ndarray, n: int = HORIZON, rng: np.random.Generator | None = None) -> np.ndarray:
    """(n, 3) the teacher's desired gripper positions for a cube at ``cube`` (see the module docstring).

    :param cube: the cube's centre (3,).
    :param n: steps.
    :param rng: draws the approach's via point (None: straight over the midpoint, 3 cm higher).
    """
    grasp = keyframes(np.asarray(cube, np.float64))
    wiggle = (np.array([0.0, 0.0, 0.03]) if rng is None else
              np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.06, 0.06), rng.uniform(0.0, 0.06)]))
    via = (START + grasp[0][1]) / 2 + wiggle
    return through([(0.0, START), (0.15, via), *grasp, (1.0, grasp[-1][1])], n)


def teacher_demos(m: int = 6, n: int = HORIZON, seed: int = 0) -> np.ndarray:
    """(m, n, 3) the scripted teacher's demonstrations, demonstration k with the cube at ``demo_cubes(m, seed)[k]``.

    :param m: demonstrations.
    :param n: steps each.
    :param seed: seed of the cube's places and the approaches' via points.
    """
    rng = np.random.default_rng(seed)
    return np.stack([teacher_plan(c, n, rng) for c in demo_cubes(m, seed)])


def describe(obs: np.ndarray) -> dict[str, float]:
    """The scene: the cube's x, y (metres) in the episode's first observation.

    :param obs: the environment's observation (21,), or ``panda:pick-pixels``' dict.
    """
    cube = cube_of(obs)
    return {"cube_x": float(cube[0]), "cube_y": float(cube[1])}


def via_points(obs: np.ndarray, n: int = HORIZON) -> list[ViaPoint]:
    """The grasp at the observed cube: the teacher's plan for the cube in the first observation at the 16 phases
    ``VIA_PHASES`` (above the cube, down onto it, held there, lifted), precision 1e6 (1 mm).

    :param obs: the environment's observation (21,), or ``panda:pick-pixels``' dict.
    :param n: N, the steps of the task's episodes (the grid the phases snap to).
    """
    plan = teacher_plan(cube_of(obs), n)
    steps = np.unique(np.round(VIA_PHASES * (n - 1)).astype(int))
    return [ViaPoint(float(t) / (n - 1), tuple(float(v) for v in plan[t])) for t in steps]


class PandaGuide:
    """The scripted human (see the module docstring): P_h over the observed cube during the grasp part of the task
    (phase in [``PHASES["above"]``, ``PHASES["lift"]``]) while the mean is off the cube, else None."""

    def __call__(self, mean: np.ndarray, phase: float | None = None, obs: np.ndarray | None = None
                 ) -> np.ndarray | None:
        if obs is None or phase is None or not PHASES["above"] <= phase <= PHASES["lift"]:
            return None
        cube = cube_of(obs)
        if np.linalg.norm(np.asarray(mean[:2]) - cube[:2]) <= NEAR:
            return None
        return np.array([cube[0], cube[1], mean[2]], np.float64)


def make_task(scenario: str = "pick", *, horizon: int = HORIZON, seed: int = 0) -> Task:
    """gym-hil's Panda pick-cube, the cube placed at random every episode.

    :param scenario: "pick", "pick-pixels" (the same task observing gym-hil's cameras), "pick-camera" (the
        scene from the front camera) or "pick-pixels-camera" (both).
    :param horizon: N, steps per episode.
    :param seed: seed of the teacher's demonstrations.
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown panda scenario {scenario!r}; choose one of {list(SCENARIOS)}")
    sched = GripperSchedule(close_at=GRASP_PHASE, open_at=1.1)
    (x0, y0), (x1, y1) = REGION
    pixels = scenario.startswith("pick-pixels")
    env_class = {"pick-pixels": PandaPixels, "pick-camera": PandaSeen,
                 "pick-pixels-camera": partial(PandaPixels, scene_from_camera=True)}.get(scenario, PandaPosition)
    return Task(
        name=f"panda-{scenario}",
        make_env=lambda s: env_class(horizon=horizon, workspace=BOUNDS, gripper=sched, region=REGION),
        demos=teacher_demos(n=horizon, seed=seed), kmp=KMP, workspace=BOUNDS, default_scale=DEFAULT_SCALE,
        learn_scale=True, action_cost=10.0, position=tcp_of,
        push=lambda env, p_h: env.push(p_h), contact=lambda env: env.gripper_closed,
        scripted_human=PandaGuide(), success_key="succeed", reward_bound=1.0, obs_bound=10.0,
        scene=Scene(region=f"cube x in [{x0}, {x1}], y in [{y0}, {y1}] m (uniform; gym-hil's sampling bounds)",
                    describe=describe, via_points=lambda obs: via_points(obs, horizon)),
        view=View(axes=(0, 1), third=2, names=("x", "y", "z"),
                  shapes=(Cuboid("cube region", (x0, y0, 0.0), (x1, y1, 0.04)),
                          Point("region centre", tuple(DEMO_CUBE)), Point("start", tuple(START)))),
        state_key=STATE_KEY if pixels else None, image_keys=tuple(CAMERAS) if pixels else ())
