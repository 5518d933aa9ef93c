"""Fetch scenes that change every episode (issue 22): the environments of ``fetch:random`` and ``fetch:obstacle``.

:class:`FetchRandomObject` places the object uniformly in ``OBJECT_REGION`` at every reset, from the environment's
own ``np_random`` (seeded by ``reset(seed=...)``, Gymnasium's rule), rejecting places within ``MIN_START_DISTANCE``
of the gripper's start (x, y): the object never starts under the gripper's fingers. The region, x in [1.22, 1.42]
and y in [0.60, 0.90] (20 x 30 cm), lies on the table (x in [1.05, 1.55], y in [0.40, 1.10]), inside Fetch's own
placement range (the start +- 15 cm, all reachable) and is far wider than the demonstrations' band at the grasp
(< 2.4 mm, tests/unit/test_fetch_task.py). The goal stays at ``GOAL``, so that the variation is the object alone.

:class:`FetchObstacle` adds a real MuJoCo obstacle: a static box (``OBSTACLE_HALF``: 12 cm in x, 5 cm in y,
from the table top z = 0.40 to z = 0.63; across the carry, which runs mostly in +y) written into a copy of Fetch's
scene file at construction (the copy is loaded and deleted; the arm, the object and the carried object collide with
it). At every reset it stands at a random place on the demonstrations' carry path (:func:`draw_obstacle_scene`);
its centre (x, y, z) is appended to the observation.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from khgrl.common.tasks.fetch.arm import OBS_BOUND, FetchPosition, import_robotics
from khgrl.common.tasks.fetch.teacher import DEMO_OBJECT, GOAL, START, teacher_demos

__all__ = ["FetchRandomObject", "FetchObstacle", "OBJECT_REGION", "OBSTACLE_HALF", "OBSTACLE_PHASES",
           "draw_object", "draw_obstacle_scene", "box_gap", "segment_distance", "OBSTACLE_ENV_ID"]

OBJECT_REGION = ((1.22, 0.60), (1.42, 0.90))  # (x, y) low, high of the object's centre
MIN_START_DISTANCE = 0.05  # metres (x, y) between the object and the gripper's start
TABLE_TOP = 0.40
OBSTACLE_HALF = np.array([0.06, 0.025, 0.115])  # half extents: a 12 x 5 x 23 cm block standing on the table
OBSTACLE_TOP = TABLE_TOP + 2 * OBSTACLE_HALF[2]  # 0.63: above the demonstrations' carry (gripper z <= 0.613)
OBSTACLE_PHASES = (0.626, 0.747)  # where on the demonstrations' mean carry path the obstacle may stand
OBSTACLE_JITTER = 0.02  # metres, across the path
OBSTACLE_CLEARANCE = 0.05  # (x, y) from the footprint to the start and the segments start/demo object -> object
OBSTACLE_FROM_OBJECT = 0.06  # (x, y) from the footprint to the object's centre
GOAL_CLEARANCE = 0.045  # (x, y) from the footprint to the goal (the object, 2.5 cm half, placed beside it)
OBSTACLE_ENV_ID = "KhGRL/FetchPickAndPlaceObstacle-v0"


def draw_object(rng: np.random.Generator) -> np.ndarray:
    """The object's (x, y): uniform in ``OBJECT_REGION`` at least ``MIN_START_DISTANCE`` from the start.

    :param rng: the environment's ``np_random``.
    """
    low, high = (np.asarray(b, np.float64) for b in OBJECT_REGION)
    while True:
        xy = rng.uniform(low, high)
        if np.linalg.norm(xy - START[:2]) >= MIN_START_DISTANCE:
            return xy


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance from point ``p`` to the segment ``a``-``b`` (any dimension).

    :param p: the point.
    :param a: one end.
    :param b: the other end.
    """
    ab = b - a
    u = 0.0 if not np.any(ab) else float(np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + u * ab)))


def _carry_path() -> np.ndarray:
    """The demonstrations' mean path (N = 100), the carry part of which the obstacle stands on."""
    return teacher_demos().mean(axis=0)


_CARRY = _carry_path()


def box_gap(p: np.ndarray, centre: np.ndarray) -> float:
    """(x, y) distance from ``p`` to the obstacle's footprint centred at ``centre`` (0 inside).

    :param p: a point (x, y, ...).
    :param centre: the obstacle's centre (x, y, ...).
    """
    return float(np.linalg.norm(np.maximum(np.abs(np.asarray(p[:2]) - centre[:2]) - OBSTACLE_HALF[:2], 0.0)))


def _segment_gap(a: np.ndarray, b: np.ndarray, centre: np.ndarray) -> float:
    return min(box_gap(a + u * (b - a), centre) for u in np.linspace(0.0, 1.0, 41))


def _obstacle_centre(rng: np.random.Generator) -> np.ndarray:
    n = _CARRY.shape[0]
    s = rng.uniform(*OBSTACLE_PHASES) * (n - 1)
    k = int(s)
    at = _CARRY[k, :2] + (s - k) * (_CARRY[k + 1, :2] - _CARRY[k, :2])
    along = _CARRY[k + 1, :2] - _CARRY[k, :2]
    across = np.array([-along[1], along[0]]) / max(float(np.linalg.norm(along)), 1e-9)
    return at + rng.uniform(-OBSTACLE_JITTER, OBSTACLE_JITTER) * across


def draw_obstacle_scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(object (x, y), obstacle centre (x, y)): the obstacle at a uniform phase in ``OBSTACLE_PHASES`` of the
    demonstrations' mean carry path, moved up to ``OBSTACLE_JITTER`` across it, redrawn until its footprint is
    ``OBSTACLE_CLEARANCE`` from the gripper's start and ``GOAL_CLEARANCE`` from the goal; the object as in
    ``fetch:random``, redrawn until it is ``OBSTACLE_FROM_OBJECT`` from the footprint and the gripper's way to it
    (from the start, and from the demonstrations' grasp, where a mean adapted only at the grasp returns) passes
    ``OBSTACLE_CLEARANCE`` from it.

    :param rng: the environment's ``np_random``.
    """
    for _ in range(10_000):
        centre = _obstacle_centre(rng)
        if box_gap(START, centre) >= OBSTACLE_CLEARANCE and box_gap(GOAL, centre) >= GOAL_CLEARANCE:
            break
    else:  # pragma: no cover - the phases leave room
        raise RuntimeError("no obstacle place clear of the start and the goal")
    for _ in range(10_000):
        obj = draw_object(rng)
        if (box_gap(obj, centre) >= OBSTACLE_FROM_OBJECT
                and _segment_gap(START[:2], obj, centre) >= OBSTACLE_CLEARANCE
                and _segment_gap(DEMO_OBJECT[:2], obj, centre) >= OBSTACLE_CLEARANCE):
            return obj, centre
    raise RuntimeError("no object place clear of the obstacle")  # pragma: no cover - the region leaves room


class FetchRandomObject(FetchPosition):
    """``FetchPosition`` whose object is placed at random at every reset (see the module docstring).

    :param horizon: N, steps per episode.
    :param workspace: (low, high) of the commanded position.
    :param gripper: the gripper command by phase.
    :param goal: the target position (fixed).
    :param kwargs: further arguments of :class:`FetchPosition`.
    """

    def __init__(self, *, horizon: int, workspace: tuple, gripper, goal: tuple, **kwargs) -> None:
        super().__init__(horizon=horizon, workspace=workspace, gripper=gripper, object_xy=tuple(DEMO_OBJECT[:2]),
                         goal=goal, **kwargs)

    def _draw(self) -> None:
        self.object_xy = draw_object(self.np_random)

    def _place(self) -> None:
        self._draw()
        super()._place()


def _obstacle_pick_and_place(model_path: str, reward_type: str = "sparse", **kwargs):
    """gymnasium-robotics' ``FetchPickAndPlace`` (its own settings, copied from its constructor) on another scene file.

    :param model_path: the scene file (absolute).
    :param reward_type: "sparse" or "dense".
    :param kwargs: further arguments of ``MujocoFetchEnv``.
    """
    import_robotics()
    from gymnasium_robotics.envs.fetch import MujocoFetchEnv
    from gymnasium_robotics.envs.fetch.pick_and_place import MujocoFetchPickAndPlaceEnv

    env = MujocoFetchPickAndPlaceEnv.__new__(MujocoFetchPickAndPlaceEnv)
    initial_qpos = {"robot0:slide0": 0.405, "robot0:slide1": 0.48, "robot0:slide2": 0.0,
                    "object0:joint": [1.25, 0.53, 0.4, 1.0, 0.0, 0.0, 0.0]}
    MujocoFetchEnv.__init__(env, model_path=model_path, has_object=True, block_gripper=False, n_substeps=20,
                            gripper_extra_height=0.2, target_in_the_air=True, target_offset=0.0, obj_range=0.15,
                            target_range=0.15, distance_threshold=0.05, initial_qpos=initial_qpos,
                            reward_type=reward_type, **kwargs)
    return env


def _register_obstacle_env() -> None:
    if OBSTACLE_ENV_ID not in gym.registry:
        gym.register(id=OBSTACLE_ENV_ID, entry_point=_obstacle_pick_and_place, max_episode_steps=50)


def obstacle_xml(directory: Path) -> Path:
    """Fetch's pick-and-place scene file with the obstacle body added, written into ``directory`` (its includes,
    meshes and textures point at gymnasium-robotics' own files).

    :param directory: where to write it.
    """
    assets = Path(import_robotics().__file__).parent / "envs" / "assets"
    text = (assets / "fetch" / "pick_and_place.xml").read_text()
    text = text.replace('meshdir="../stls/fetch"', f'meshdir="{assets / "stls" / "fetch"}"')
    text = text.replace('texturedir="../textures"', f'texturedir="{assets / "textures"}"')
    text = re.sub(r'<include file="([^"/]+)"', lambda m: f'<include file="{assets / "fetch" / m.group(1)}"', text)
    hx, hy, hz = OBSTACLE_HALF
    body = (f'<body name="obstacle0" pos="1.35 0.87 {TABLE_TOP + hz}">'
            f'<geom name="obstacle0" type="box" size="{hx} {hy} {hz}" condim="3" rgba="0.8 0.35 0.2 1"></geom>'
            '</body>\n\t\t<light ')
    if text.count("<light ") != 1:
        raise RuntimeError("gymnasium-robotics' pick_and_place.xml changed: cannot add the obstacle")
    path = Path(directory) / "pick_and_place_obstacle.xml"
    path.write_text(text.replace("<light ", body, 1))
    return path


class FetchObstacle(FetchRandomObject):
    """``fetch:random``'s environment plus the obstacle (see the module docstring). Observation: Fetch's 28 values
    and the obstacle's centre (x, y, z); ``info["obstacle_contacts"]``: contacts with the obstacle after the step.

    :param horizon: N, steps per episode.
    :param workspace: (low, high) of the commanded position.
    :param gripper: the gripper command by phase.
    :param goal: the target position (fixed).
    """

    def __init__(self, *, horizon: int, workspace: tuple, gripper, goal: tuple) -> None:
        _register_obstacle_env()
        with tempfile.TemporaryDirectory(prefix="khgrl-fetch-") as d:
            super().__init__(horizon=horizon, workspace=workspace, gripper=gripper, goal=goal,
                             env_id=OBSTACLE_ENV_ID, env_kwargs={"model_path": str(obstacle_xml(Path(d)))})
        import mujoco

        base = self.env.unwrapped
        self._body = mujoco.mj_name2id(base.model, mujoco.mjtObj.mjOBJ_BODY, "obstacle0")
        self._geom = mujoco.mj_name2id(base.model, mujoco.mjtObj.mjOBJ_GEOM, "obstacle0")
        self.observation_space = spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(31,), dtype=np.float64)
        self.obstacle = np.array([1.35, 0.87, TABLE_TOP + OBSTACLE_HALF[2]])

    def _draw(self) -> None:
        obj, centre = draw_obstacle_scene(self.np_random)
        self.object_xy = obj
        self.obstacle = np.array([centre[0], centre[1], TABLE_TOP + OBSTACLE_HALF[2]])
        self.env.unwrapped.model.body_pos[self._body] = self.obstacle  # a static body: mj_forward moves it

    def _flat(self) -> np.ndarray:
        return np.concatenate([super()._flat(), np.clip(self.obstacle, -OBS_BOUND, OBS_BOUND)])

    def contacts(self) -> int:
        """Contacts between the obstacle and anything (the arm, the object) now."""
        data = self.env.unwrapped.data
        g = self._geom
        return int(sum(1 for c in data.contact[:data.ncon] if g in (c.geom1, c.geom2)))

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        info["obstacle_contacts"] = self.contacts()
        return obs, reward, terminated, truncated, info
