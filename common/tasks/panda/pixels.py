"""gym-hil's Panda pick-cube with camera observations: the environment of ``--task panda:pick-pixels`` (issue 37).

:class:`PandaPixels` is :class:`~khgrl.common.tasks.panda.arm.PandaPosition` (the same adapter, cube placement,
reward and episode end) observing what gym-hil's ``image_obs=True`` observes: ``front`` and ``wrist`` (gym-hil's
``front`` and ``handcam_rgb`` cameras, 128 x 128 x 3 uint8 by default) and ``agent_pos`` (18: joint angles and
velocities, the gripper command scaled to [0, 1], the pinch site's position; the task's state vector), plus
``environment_state``, the cube's true position (3), which the policy does not observe (it is not one of the
task's ``image_keys`` nor its ``state_key``: :mod:`khgrl.common.tasks.obs_spaces`): only the task's own functions
read it -- the scene's placement and via-points and the scripted human, as in ``panda:pick`` (:func:`cube_of`).

Rendering: gym-hil's own ``image_obs`` path renders both cameras with its ``mujoco.Renderer`` at the model's
settings (shadow map 4096, 8 samples); here one renderer made by
:func:`~khgrl.common.tasks.panda.camera.front_renderer` (shadows and reflections off, no multisampling) renders both
cameras after every reset and step. Measured by ``python -m khgrl.benchmarks.pixels_step`` (ms per env step).

``scene_from_camera`` (``panda:pick-pixels-camera``): the first observation's ``environment_state`` holds the cube's
(x, y) located in that observation's own ``front`` frame (:class:`~khgrl.common.tasks.panda.seen.CubeSight`, as
``panda:pick-camera`` locates it), so the scene and its via-points come from what the policy's camera sees.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from khgrl.common.tasks.panda.arm import CUBE, TCP, PandaPosition

__all__ = ["PandaPixels", "CAMERAS", "STATE_KEY", "PRIVILEGED_KEY", "IMAGE_SIZE", "cube_of", "tcp_of"]

CAMERAS = {"front": "front", "wrist": "handcam_rgb"}  # image key -> gym-hil's camera name (its image_obs keys)
STATE_KEY = "agent_pos"  # gym-hil's robot state (the first 18 entries of PandaPosition's observation)
PRIVILEGED_KEY = "environment_state"  # the cube's true position: the task's functions read it, the policy does not
IMAGE_SIZE = 128  # gym-hil's GymRenderingSpec default
AGENT = slice(0, 18)


def cube_of(obs: Any) -> np.ndarray:
    """The cube's position (3,) in a ``panda:pick`` (flat) or ``panda:pick-pixels`` (dict) observation.

    :param obs: the environment's observation.
    """
    if isinstance(obs, dict):
        return np.asarray(obs[PRIVILEGED_KEY], np.float64)
    return np.asarray(obs, np.float64)[CUBE]


def tcp_of(obs: Any) -> np.ndarray:
    """The pinch site's position (3,) in a ``panda:pick`` (flat) or ``panda:pick-pixels`` (dict) observation.

    :param obs: the environment's observation.
    """
    if isinstance(obs, dict):
        return np.asarray(obs[STATE_KEY], np.float64)[TCP]
    return np.asarray(obs, np.float64)[TCP]


class PandaPixels(PandaPosition):
    """:class:`~khgrl.common.tasks.panda.arm.PandaPosition` observing cameras (see the module docstring).

    :param size: height and width of each image (pixels).
    :param scene_from_camera: the first observation's ``environment_state`` holds the cube's (x, y) as the front
        frame of that observation shows it (:class:`~khgrl.common.tasks.panda.seen.CubeSight`; ``info["cube_seen"]``),
        not its true place: the scene, via-points and scripted human then start from what the camera sees.
    :param kwargs: :class:`~khgrl.common.tasks.panda.arm.PandaPosition`'s parameters.
    """

    def __init__(self, size: int = IMAGE_SIZE, *, scene_from_camera: bool = False, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        from khgrl.common.tasks.panda.camera import front_renderer
        from khgrl.common.tasks.panda.seen import CubeSight

        self.size = int(size)
        self._renderer = front_renderer(self.base.model, self.size)
        self.sight = CubeSight(self.base.model, self.region) if scene_from_camera else None
        image = spaces.Box(0, 255, shape=(self.size, self.size, 3), dtype=np.uint8)
        self.observation_space = spaces.Dict({
            STATE_KEY: spaces.Box(self._low[AGENT], self._high[AGENT], dtype=np.float64),
            PRIVILEGED_KEY: spaces.Box(self._low[CUBE], self._high[CUBE], dtype=np.float64),
            **{key: image for key in CAMERAS}})

    def _observe(self, flat: np.ndarray) -> dict[str, np.ndarray]:
        """The dict observation from the flat one and the cameras now."""
        out = {STATE_KEY: flat[AGENT].copy(), PRIVILEGED_KEY: flat[CUBE].copy()}
        for key, camera in CAMERAS.items():
            self._renderer.update_scene(self.base.data, camera=camera)
            out[key] = np.asarray(self._renderer.render(), np.uint8).copy()
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        flat, info = super().reset(seed=seed, options=options)
        obs = self._observe(flat)
        if self.sight is None:
            return obs, info
        from khgrl.common.tasks.panda.camera import camera_of

        camera = camera_of(self.base.model, self.base.data, "front")
        seen, found = self.sight.place(obs["front"], camera, obs[PRIVILEGED_KEY][:2].copy())
        obs[PRIVILEGED_KEY][:2] = seen
        return obs, {**info, "cube_seen": found}

    def step(self, action):
        flat, reward, terminated, truncated, info = super().step(action)
        return self._observe(flat), reward, terminated, truncated, info

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()
