"""A small task whose scene changes every episode (issue 22), for the tests of ``khgrl eval --scenes``: a point
robot in 2-D goes from a fixed start to a goal that its environment places at random at each reset (from its own
``np_random``, Gymnasium's rule) in ``GOAL_LOW``..``GOAL_HIGH``. The observation is (robot x, y, goal x, y); the
task's ``Scene`` reads the goal from it and pins the KMP's end to it (a via-point at phase 1).

It is a module of its own so that the integration test can copy it into a scratch folder and give it to
``khgrl up --task scene_point_task:make_task`` like a user's task.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from khgrl.common.tasks.scene import Scene, ViaPoint

from khgrl.task import KMPConfig, Point, Task, View

START = np.array([0.1, 0.5])
GOAL_LOW, GOAL_HIGH = np.array([0.7, 0.3]), np.array([0.9, 0.7])
SPEED, GOAL_RADIUS, N = 0.05, 0.06, 40


class ScenePoint2D(gym.Env):
    """Action: the desired position (2,); observation: robot (2,) and goal (2,); +100 and the end at the goal."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(0.0, 1.0, shape=(4,), dtype=np.float64)
        self.action_space = gym.spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float64)
        self.robot, self.goal = START.copy(), (GOAL_LOW + GOAL_HIGH) / 2

    def _obs(self) -> np.ndarray:
        return np.concatenate([self.robot, self.goal])

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.robot = START.copy()
        self.goal = self.np_random.uniform(GOAL_LOW, GOAL_HIGH)
        return self._obs(), {}

    def step(self, action):
        step = np.clip(np.asarray(action, dtype=np.float64), 0.0, 1.0) - self.robot
        dist = float(np.linalg.norm(step))
        self.robot = self.robot + (step if dist <= SPEED else step * (SPEED / dist))
        success = bool(np.linalg.norm(self.robot - self.goal) <= GOAL_RADIUS)
        return self._obs(), 100.0 if success else 0.0, success, False, {"success": success}


def make_demos(m: int = 6, seed: int = 0) -> np.ndarray:
    """(m, N, 2) minimum-jerk paths from the start to goals spread over the goal region (as a demonstrator would
    show them): their spread at the end is what lets a via-point at the goal move the KMP's end."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, N)[:, None]
    progress = 10 * s**3 - 15 * s**4 + 6 * s**5
    return np.stack([START + (rng.uniform(GOAL_LOW, GOAL_HIGH) - START) * progress for _ in range(m)])


def make_task() -> Task:
    """The task (``--task scene_point_task:make_task``)."""
    return Task(name="scene-point-2d", make_env=lambda seed: ScenePoint2D(), demos=make_demos(),
                kmp=KMPConfig(length_scale=0.1),  # (4 of the 40 steps wide: a via-point moves its neighbours too)
                workspace=((0.0, 0.0), (1.0, 1.0)), default_scale=0.1, learn_scale=False, reward_bound=100.0,
                position=lambda obs: obs[:2],
                scene=Scene(region="goal x in [0.7, 0.9], y in [0.3, 0.7] (uniform)",
                            describe=lambda obs: {"goal_x": float(obs[2]), "goal_y": float(obs[3])},
                            via_points=lambda obs: [ViaPoint(1.0, obs[2:4])]),
                view=View(names=("x", "y"), shapes=(Point("start", tuple(START)),)))
