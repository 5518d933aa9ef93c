"""gym-hil's Panda pick-cube whose scene is what the front camera sees: the environment of ``--task
panda:pick-camera`` (issue 37, point 5).

``panda:pick`` reads the cube's place for its via-points (and its placement) from the first observation, which
holds the cube's true position: a real robot has only a camera. :class:`PandaSeen` is
:class:`~khgrl.common.tasks.panda.arm.PandaPosition` whose *first* observation of an episode holds, instead of the
cube's true (x, y), the estimate from one 128 x 128 frame of gym-hil's ``front`` camera
(:func:`~khgrl.common.tasks.panda.camera.locate_cube`: colour segmentation, back-projection onto the table, the
arm's occlusion modelled): the scene's placement, the via-points and the KMP refitted through them follow the
camera. From the first step on the observation is ``panda:pick``'s, so a policy trained on ``panda:pick`` sees
what it was trained on and only the scene's source differs (``khgrl eval RUN --task panda:pick-camera``).
:class:`CubeSight` is the estimate and its counts; ``panda:pick-pixels-camera`` (:class:`~khgrl.common.tasks.panda.
pixels.PandaPixels` with ``scene_from_camera``) takes it from the front frame its policy sees.

A cube the camera does not find (:class:`~khgrl.common.tasks.panda.camera.CubeNotFound`: 13 of 200 scenes in
docs/camera_scene.json) is reached for where the region's centre is -- what a robot that saw nothing would do --
and counted (``not_seen``, ``info["cube_seen"]`` False). The reset costs one render (~170 ms) and the estimate
(~55 ms) more than ``panda:pick``'s; the reset's random draws are the same, so seeded scenes place the cube where
``panda:pick`` does.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from khgrl.common.tasks.panda.arm import CUBE, PandaPosition

__all__ = ["PandaSeen", "CubeSight"]


class CubeSight:
    """The cube's (x, y) as the front camera sees it at a reset, or the region's centre where it is not found, with
    the counts (see the module docstring).

    :param model: the ``mujoco.MjModel`` (its materials' colours).
    :param region: the cube's sampling region ((x0, y0), (x1, y1)), or None (then a cube not found is reached for
        at its true place).
    """

    def __init__(self, model, region) -> None:
        from khgrl.common.tasks.panda.colours import scene_colours

        self._colours = scene_colours(model)
        self.region = region
        self.seen = 0
        self.not_seen = 0
        self.last_error_m = float("nan")  # |estimate - truth| in (x, y) at the last reset where the cube was seen

    def place(self, frame: np.ndarray, camera, truth: np.ndarray) -> tuple[np.ndarray, bool]:
        """(the cube's (x, y) to act on, whether the camera found it) from one front frame.

        :param frame: the front camera's frame (H, W, 3) uint8.
        :param camera: the camera it was taken with (:func:`~khgrl.common.tasks.panda.camera.camera_of`).
        :param truth: the cube's true (x, y): counted against the estimate, never returned.
        """
        from khgrl.common.tasks.panda.camera import CubeNotFound, locate_cube

        try:
            seen = locate_cube(frame, camera, self._colours)[:2]
        except CubeNotFound:
            self.not_seen += 1
            low, high = self.region if self.region is not None else (truth, truth)
            return (np.asarray(low, np.float64) + np.asarray(high, np.float64)) / 2, False
        self.seen += 1
        self.last_error_m = float(np.linalg.norm(seen - truth))
        return seen, True


class PandaSeen(PandaPosition):
    """:class:`~khgrl.common.tasks.panda.arm.PandaPosition` whose first observation holds the cube as the front
    camera sees it (see the module docstring).

    :param kwargs: :class:`~khgrl.common.tasks.panda.arm.PandaPosition`'s parameters.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        from khgrl.common.tasks.panda.camera import front_renderer

        self._renderer = front_renderer(self.base.model)
        self.sight = CubeSight(self.base.model, self.region)

    @property
    def seen(self) -> int:
        """Resets where the camera found the cube."""
        return self.sight.seen

    @property
    def not_seen(self) -> int:
        """Resets where it did not."""
        return self.sight.not_seen

    @property
    def last_error_m(self) -> float:
        """|estimate - truth| in (x, y) at the last reset where the cube was seen (metres)."""
        return self.sight.last_error_m

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        from khgrl.common.tasks.panda.camera import render_front

        flat, info = super().reset(seed=seed, options=options)
        frame, camera = render_front(self._renderer, self.base.model, self.base.data)
        seen, found = self.sight.place(frame, camera, flat[CUBE][:2].copy())
        flat[CUBE.start:CUBE.start + 2] = seen
        return flat, {**info, "cube_seen": found}

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()
