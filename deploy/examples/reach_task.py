"""A task whose scene changes every episode, in 40 lines of task definition: a 2-D point robot reaches a target
that is placed at random at every reset (``--task khgrl.deploy.examples.reach_task:make_task``).

The demonstrations all end at ``DEMO_TARGET``; the target is drawn uniformly from ``REGION`` (seeded by the
reset's seed), mostly outside the demonstrations' spread. The scene adapts the KMP with via-points: the last
quarter of the movement re-targeted, on a straight line from the start to the observed target (one via-point alone
would move only its own grid step: the demonstrations agree closely at their end). Without adaptation the mean ends
at ``DEMO_TARGET``.

Action: the desired position P_t (2,) in the workspace [-1, 1]^2; the robot moves there. Observation: position (2)
and target (2). Reward: -|position - target| per step. Success: within 5 cm of the target at the last step.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from khgrl.common.tasks.api import Point, Scene, Task, ViaPoint, View

__all__ = ["ReachEnv", "make_task", "REGION", "DEMO_TARGET"]

HORIZON = 40
START = np.array([-0.6, 0.0])
DEMO_TARGET = np.array([0.5, 0.0])
REGION = ((0.3, -0.6), (0.7, 0.6))  # the target's (x, y) range: uniform


class ReachEnv(gym.Env):
    """A point robot that goes where it is told; the target moves every episode (see the module docstring)."""

    def __init__(self, horizon: int = HORIZON) -> None:
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float64)
        self.observation_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float64)
        self.horizon = horizon
        self.pos, self.target, self.t = START.copy(), DEMO_TARGET.copy(), 0

    def _obs(self) -> np.ndarray:
        return np.concatenate([self.pos, self.target])

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.target = self.np_random.uniform(REGION[0], REGION[1])
        self.pos, self.t = START.copy(), 0
        return self._obs(), {}

    def step(self, action):
        self.pos = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
        self.t += 1
        dist = float(np.linalg.norm(self.pos - self.target))
        done = self.t >= self.horizon
        return self._obs(), -dist, False, done, {"success": bool(done and dist < 0.05)}


def demos(m: int = 5, n: int = HORIZON, seed: int = 0) -> np.ndarray:
    """(m, n, 2) straight-ish movements from START to DEMO_TARGET with a random bow."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n)[:, None]
    line = START + s * (DEMO_TARGET - START)
    return np.stack([line + np.sin(np.pi * s) * [0.0, rng.uniform(-0.3, 0.3)] for _ in range(m)])


def via_points(obs: np.ndarray) -> list[ViaPoint]:
    """The last quarter of the movement, on the line from START to the observed target (obs[2:4])."""
    target = np.asarray(obs[2:4], np.float64)
    return [ViaPoint(s, START + s * (target - START), 1e6) for s in np.linspace(0.75, 1.0, 11)]


def make_task() -> Task:
    return Task(name="reach", make_env=lambda seed: ReachEnv(), demos=demos(), workspace=((-1.0, -1.0), (1.0, 1.0)),
                default_scale=5.0, action_cost=0.0, position=lambda obs: obs[:2],
                scene=Scene(region=f"target x in [{REGION[0][0]}, {REGION[1][0]}], y in [{REGION[0][1]}, "
                                   f"{REGION[1][1]}] (uniform)",
                            describe=lambda obs: {"target_x": float(obs[2]), "target_y": float(obs[3])},
                            via_points=via_points),
                view=View(shapes=(Point("start", tuple(START)), Point("demo target", tuple(DEMO_TARGET)))))
