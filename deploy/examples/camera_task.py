"""A camera task that costs nothing to render: the passage world (``passage:high_cov``) observed as a state vector
and one tiny image (``--task khgrl.deploy.examples.camera_task:make_task``).

:class:`CameraRobot` wraps the passage world's robot: its observation is ``{"pos": the robot's position (2,),
"cam": a SIDE x SIDE x 3 uint8 image, black with the robot as one white pixel}``. The task declares ``pos`` its
state vector and ``cam`` its camera (:mod:`khgrl.common.tasks.obs_spaces`), so the policy observes a Dict of
``"state"`` (position, phase, deviation) and ``"cam"``. It exercises the camera path of the whole system -- the
task descriptor's ``cameras``, the wire's frames, the actor's image policy, the learner's frame replay -- without
MuJoCo, at the passage world's speed; the tests use it (tests/unit/test_pixels_task.py,
tests/integration/test_camera_run.py).
"""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from khgrl.common.tasks.api import Task, load_task

__all__ = ["CameraRobot", "make_task", "make_two_cameras", "SIDE"]

SIDE = 16  # the image's side, pixels


class CameraRobot(gym.Env):
    """The passage robot observed as ``{"pos": position (2,), "cam": an image of the robot as a white dot}``;
    ``images`` overrides the image spaces it declares (tests of refused declarations).

    :param robot: the passage world's robot.
    :param images: key -> image space (default: ``cam``, SIDE x SIDE x 3 uint8).
    """

    metadata = {"render_modes": []}

    def __init__(self, robot: gym.Env, images: dict | None = None) -> None:
        self.robot = robot
        self.images = images or {"cam": spaces.Box(0, 255, (SIDE, SIDE, 3), np.uint8)}
        self.observation_space = spaces.Dict({"pos": robot.observation_space, **self.images})
        self.action_space = robot.action_space

    def _observe(self, pos: np.ndarray) -> dict:
        out = {"pos": pos}
        for key, box in self.images.items():  # each declared image: black, the robot a white dot
            h, w = box.shape[:2]
            img = np.zeros(box.shape, np.uint8)
            r, c = (np.clip(pos, 0.0, 1.0) * (np.array([w, h]) - 1)).round().astype(int)
            img[h - 1 - c, r] = 255
            out[key] = img
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """The robot's reset, observed.

        :param seed: the reset's seed
        :param options: unused
        """
        super().reset(seed=seed)
        pos, info = self.robot.reset(seed=seed)
        return self._observe(pos), info

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """The robot's step, observed.

        :param action: the desired position
        """
        pos, reward, term, trunc, info = self.robot.step(action)
        return self._observe(pos), reward, term, trunc, info


def make_task(images: dict | None = None, state_key: str | None = "pos", image_keys: tuple = ("cam",)) -> Task:
    """``passage:high_cov`` observing :class:`CameraRobot` (the arguments: other declarations, for tests).

    :param images: the image spaces the environment declares (None: ``cam``)
    :param state_key: the state vector's key the task declares
    :param image_keys: the image keys the task declares
    """
    base = load_task("passage:high_cov")
    return replace(base, name="passage-camera", make_env=lambda s: CameraRobot(base.make_env(s), images),
                   position=lambda obs: obs["pos"], scripted_human=None, state_key=state_key,
                   image_keys=tuple(image_keys))


def make_two_cameras(side: int = 128) -> Task:
    """The same world seen by two ``side`` x ``side`` RGB cameras, ``front`` and ``wrist`` (the size of gym-hil's
    Panda): what ``khgrl bench images`` sends (``--task khgrl.deploy.examples.camera_task:make_two_cameras``).

    :param side: each image's side, pixels
    """
    box = spaces.Box(0, 255, (side, side, 3), np.uint8)
    return make_task({"front": box, "wrist": box}, image_keys=("front", "wrist"))
