"""The passage world's observation and action spaces, defined once (the actor's environment, the learner's
spaces-only environment and the wire schema all use these)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

__all__ = ["OBS_DIM", "ACT_DIM", "observation_space", "action_space", "SpacesEnv"]

OBS_DIM = 5  # (x, y, phase, deviation from the KMP mean in x and y); see common.env.PassageEnv
ACT_DIM = 2  # the null-space action a in [-1, 1]^2 (paper eq. 5)


def observation_space() -> spaces.Box:
    return spaces.Box(low=np.array([0.0, 0.0, 0.0, -1.0, -1.0], dtype=np.float32),
                      high=np.array([1.0, 1.0, 1.0, 1.0, 1.0], dtype=np.float32), dtype=np.float32)


def action_space() -> spaces.Box:
    return spaces.Box(-1.0, 1.0, shape=(ACT_DIM,), dtype=np.float32)


class SpacesEnv(gym.Env):
    """An environment that has only the spaces: the learner never steps an environment (transitions come
    from actors), but SB3 builds its model from an environment's spaces."""

    metadata = {"render_modes": []}

    def __init__(self) -> None:
        self.observation_space, self.action_space = observation_space(), action_space()

    def reset(self, *, seed=None, options=None):  # noqa: ARG002
        raise RuntimeError("the learner's environment has spaces only: transitions come from actors")

    def step(self, action):  # noqa: ARG002
        raise RuntimeError("the learner's environment has spaces only: transitions come from actors")
