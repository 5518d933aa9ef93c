"""A task for the tests of the limits on what the robot is sent (issue 33): the passage world (``low_cov``) whose
``command`` and ``hold`` adapters log every command its driver gets, as a robot's driver would see them.

``KHGRL_DRIVER_LOG`` names the log (one line per command, appended and flushed at once):

* ``reset TIME N X Y``: the environment's N-th reset; the robot is at (X, Y);
* ``step TIME N K X Y``: the K-th position sent since reset N (episode steps, then the path back to the start);
* ``hold TIME N X Y RX RY``: the actor holds the robot at (X, Y), the position last sent; the robot is measured at
  (RX, RY) (the adapter returns that observation);
* ``push TIME N RX RY``: a hand moved the robot to (RX, RY) while it was held.

A hand on the arm: when the file ``KHGRL_DRIVER_PUSH`` names appears, the next hold moves the robot by :data:`PUSH`
(once), as a person would while the e-stop holds it. It is a module of its own so that ``khgrl up --task
driver_log_task:make_task`` loads it in every process, with this folder on PYTHONPATH, like a user's task.
"""

from __future__ import annotations

import os
import time
from dataclasses import replace

import gymnasium as gym
import numpy as np
from khgrl.common.tasks.passage.task import make_task as passage_task

PUSH = np.array([0.0, 0.04])  # along y: a vertical wall of the passage world is never crossed


class DriverLog(gym.Wrapper):
    """The passage robot behind a driver that logs what it gets (module docstring)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        path = os.environ.get("KHGRL_DRIVER_LOG")
        self.log = open(path, "a", buffering=1) if path else None  # noqa: SIM115 - open for the process's life
        self.push_file = os.environ.get("KHGRL_DRIVER_PUSH", "")
        self.resets, self.k, self.pushed = 0, 0, False

    def write(self, *fields) -> None:
        if self.log is not None:
            self.log.write(" ".join(f"{x:.12g}" if isinstance(x, float) else str(x) for x in fields) + "\n")

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.resets, self.k = self.resets + 1, 0
        self.write("reset", time.time(), self.resets, *map(float, obs))
        return obs, info

    def command(self, p: np.ndarray) -> np.ndarray:
        self.write("step", time.time(), self.resets, self.k, *map(float, p))
        self.k += 1
        return p

    def hold(self, p: np.ndarray) -> np.ndarray:
        robot = self.env.unwrapped
        if self.push_file and not self.pushed and os.path.exists(self.push_file):
            robot.robot = np.clip(robot.robot + PUSH, 0.0, 1.0)
            self.pushed = True
            self.write("push", time.time(), self.resets, *map(float, robot.robot))
        self.write("hold", time.time(), self.resets, *map(float, p), *map(float, robot.robot))
        return robot.robot.copy()  # the observation: the robot measured while held


def make_task():
    """The task (``--task driver_log_task:make_task``)."""
    base = passage_task("low_cov")
    return replace(base, name="passage-low_cov-logged", make_env=lambda seed: DriverLog(base.make_env(seed)),
                   command=lambda env, p: env.command(p), hold=lambda env, p: env.hold(p))


def read_log(path) -> list[tuple]:
    """The log's lines as tuples (kind, time, reset, numbers...)."""
    out = []
    for line in open(path).read().splitlines():
        kind, *rest = line.split()
        out.append((kind, float(rest[0]), int(rest[1]), *(float(x) for x in rest[2:])))
    return out
