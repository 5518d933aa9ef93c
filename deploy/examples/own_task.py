"""A minimal own task (README, "Bring your own task"): a point robot in 3-D goes around a keep-out box.

``khgrl up --task khgrl.deploy.examples.own_task:make_task --episodes 20`` trains on it. The environment's action is
the desired position (x, y, z); the robot moves toward it at most ``SPEED`` per step and stops at the face of
the box it would enter (reward -10 while blocked); reaching the goal gives +200 and ends the episode. The six
demonstrations go from start to goal, some of them lifting over the box: RL (or a human) finds the way over.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from khgrl.task import Cuboid, Point, Task, View

START, GOAL = np.array([0.1, 0.5, 0.1]), np.array([0.9, 0.5, 0.1])
BOX_LOW, BOX_HIGH = np.array([0.4, 0.3, 0.0]), np.array([0.6, 0.7, 0.3])  # the keep-out box
SPEED, GOAL_RADIUS = 0.02, 0.05


def box_entry(p: np.ndarray, q: np.ndarray) -> float | None:
    """The fraction of the segment p -> q at which it enters the keep-out box (None: it does not)."""
    d = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (BOX_LOW - p) / d, (BOX_HIGH - p) / d
    inside = (p > BOX_LOW) & (p < BOX_HIGH)  # a zero-length axis: inside its slab or never
    lo = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max()
    hi = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min()
    return float(lo) if lo < hi and 0.0 <= lo <= 1.0 else None


class PointRobot3D(gym.Env):
    """Action: the desired position (3,); observation: the robot position (3,)."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float64)
        self.action_space = gym.spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float64)
        self.robot = START.copy()

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.robot = START.copy()
        return self.robot.copy(), {}

    def step(self, action):
        step = np.clip(np.asarray(action, dtype=np.float64), 0.0, 1.0) - self.robot
        dist = float(np.linalg.norm(step))
        target = self.robot + (step if dist <= SPEED else step * (SPEED / dist))
        enter = box_entry(self.robot, target)
        blocked = enter is not None
        if blocked:  # stop just short of the face it would cross
            target = self.robot + max(enter - 1e-6, 0.0) * (target - self.robot)
        self.robot = target
        success = bool(np.linalg.norm(self.robot - GOAL) <= GOAL_RADIUS)
        reward = (-10.0 if blocked else 0.0) + (200.0 if success else 0.0)
        return self.robot.copy(), reward, success, False, {"success": success, "blocked": blocked}


def make_demos(m: int = 6, n: int = 200, seed: int = 0) -> np.ndarray:
    """(m, n, 3) smooth start -> goal paths; their height over the middle fans out (some clear the box)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n)[:, None]
    progress = 10 * s**3 - 15 * s**4 + 6 * s**5  # minimum jerk
    demos = np.empty((m, n, 3))
    for k, lift in enumerate(np.linspace(0.0, 0.35, m)):
        bump = np.sin(np.pi * progress) * [0.0, rng.uniform(-0.08, 0.08), lift + rng.uniform(-0.02, 0.02)]
        demos[k] = START + (GOAL - START) * progress + bump
    return demos


def lift_over_box(mean: np.ndarray) -> np.ndarray | None:
    """The scripted human: near the box, hold the desired position above it; elsewhere let go."""
    if not BOX_LOW[0] - 0.1 <= mean[0] <= BOX_HIGH[0] + 0.1:
        return None
    return np.array([mean[0], mean[1], max(mean[2], BOX_HIGH[2] + 0.08)])


def make_task() -> Task:
    """The task (``--task khgrl.deploy.examples.own_task:make_task``)."""
    return Task(name="point-3d", make_env=lambda seed: PointRobot3D(), demos=make_demos(),
                workspace=((0.02, 0.02, 0.02), (0.98, 0.98, 0.8)), default_scale=5.0, learn_scale=True,
                position=lambda obs: obs, scripted_human=lift_over_box,
                view=View(axes=(0, 1), third=2, names=("x", "y", "z"),
                          shapes=(Cuboid("keep-out", tuple(BOX_LOW), tuple(BOX_HIGH)),
                                  Point("start", tuple(START)), Point("goal", tuple(GOAL)))))
