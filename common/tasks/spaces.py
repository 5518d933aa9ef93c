"""The policy's spaces: from a run's task descriptor, or the passage world's (5 observations, 2 actions) when no
descriptor is given. The learner's spaces-only environment is built from them."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from khgrl.common.wire.descriptor import STATE

__all__ = ["OBS_DIM", "ACT_DIM", "observation_space", "action_space", "SpacesEnv"]

OBS_DIM = 5  # the passage world: (x, y, phase, deviation from the KMP mean in x and y); see passage.env.PassageEnv
ACT_DIM = 2  # the passage world's null-space action a in [-1, 1]^2 (paper eq. 5)


def observation_space(task=None) -> spaces.Box | spaces.Dict:
    """The policy's observation space: a Box, or for a camera task (``task.cameras``) a Dict of the ``"state"`` Box
    and each camera's uint8 (H, W, C) Box -- what the actor's :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` observes.

    :param task: a :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: the passage world's).
    """
    if task is None:
        return spaces.Box(low=np.array([0.0, 0.0, 0.0, -1.0, -1.0], dtype=np.float32),
                          high=np.array([1.0, 1.0, 1.0, 1.0, 1.0], dtype=np.float32), dtype=np.float32)
    low = np.asarray(task.obs_low, dtype=np.float64)
    high = np.asarray(task.obs_high, dtype=np.float64)
    state = spaces.Box(low=np.where(low <= -1e30, -np.inf, low).astype(np.float32),
                       high=np.where(high >= 1e30, np.inf, high).astype(np.float32), dtype=np.float32)
    cameras = getattr(task, "cameras", None)
    if not cameras:
        return state
    images = {k: spaces.Box(0, 255, tuple(shape), np.uint8) for k, shape in cameras.items()}
    return spaces.Dict({STATE: state, **images})


def action_space(task=None) -> spaces.Box:
    """The policy's action space: [-1, 1]^O (eq. 5).

    :param task: a :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: the passage world's, O = 2).
    """
    return spaces.Box(-1.0, 1.0, shape=(ACT_DIM if task is None else task.out_dim,), dtype=np.float32)


class SpacesEnv(gym.Env):
    """An environment that has only the spaces: the learner never steps an environment (transitions come
    from actors), but SB3 builds its model from an environment's spaces.

    :param task: the run's task descriptor (None: the passage world's spaces).
    """

    metadata = {"render_modes": []}

    def __init__(self, task=None) -> None:
        self.observation_space, self.action_space = observation_space(task), action_space(task)

    def reset(self, *, seed=None, options=None):  # noqa: ARG002
        raise RuntimeError("the learner's environment has spaces only: transitions come from actors")

    def step(self, action):  # noqa: ARG002
        raise RuntimeError("the learner's environment has spaces only: transitions come from actors")
