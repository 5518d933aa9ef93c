"""The animation of evaluation episodes (``khgrl eval --gif``; with ``--scenes`` several scenes one after another)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["GifRecorder", "GIF_SIZE"]

GIF_SIZE = (720, 360)


class GifRecorder:
    """Frames of one episode drawn by :class:`khgrl.common.tasks.render.TaskRenderer` -- beside the simulator's own
    camera
    view where the task's environment has one (``camera_frame(size)``, e.g. the Fetch arm) -- as an animated GIF.

    :param env: the evaluation environment (its descriptor sets up the drawing).
    :param every: keep every ``every``-th step.
    """

    def __init__(self, env: Any, every: int = 1) -> None:
        from khgrl.common.tasks.render import TaskRenderer, frame_from_env

        self.renderer = TaskRenderer(env.descriptor(env.task.name), size=GIF_SIZE)
        self.frame_from_env = frame_from_env
        self.every = max(1, int(every))
        self.frames: list[np.ndarray] = []
        self.calls = 0
        self.camera = callable(getattr(env.inner, "camera_frame", None))  # the simulator's own view, if it has one
        self.caption = ""

    def next_episode(self, caption: str = "") -> None:
        """The next call is an episode's first frame (kept whatever ``every``): one GIF shows several episodes.

        :param caption: a line written on this episode's frames (e.g. the scene and its placement; "" none).
        """
        self.calls = 0
        self.caption = caption

    def __call__(self, env: Any, done: bool) -> None:
        if self.calls % self.every == 0 or done:  # the last frame always
            img = self.renderer.render_rgb(self.frame_from_env(env))
            if self.caption:
                img = _captioned(img, self.caption)
            camera = self._camera(env, img.shape[0]) if self.camera else None
            self.frames.append(img if camera is None else np.concatenate([camera, img], axis=1))
        self.calls += 1

    def _camera(self, env: Any, size: int) -> np.ndarray | None:
        """The simulator's view (MuJoCo offscreen), or None from the first failure on (no OpenGL here)."""
        try:
            return env.inner.camera_frame(size)
        except Exception as exc:  # noqa: BLE001 - any GL error: the task's views alone
            self.camera = False
            print(f"khgrl eval: the GIF shows the task's views only (no camera view: {exc})", file=sys.stderr)
            return None

    def save(self, path: Path, fps: int = 20) -> int:
        """Write the frames to ``path``; returns how many.

        :param path: the GIF file.
        :param fps: frames per second of the animation.
        """
        from PIL import Image

        images = [Image.fromarray(np.ascontiguousarray(f, dtype=np.uint8)) for f in self.frames]
        first = images[0].quantize(colors=255, method=Image.Quantize.MEDIANCUT)  # one palette: no colour flicker
        rest = [im.quantize(palette=first, dither=Image.Dither.NONE) for im in images[1:]]
        path.parent.mkdir(parents=True, exist_ok=True)
        first.save(path, save_all=True, append_images=rest, duration=int(1000 / fps), loop=0)
        return len(images)


def _captioned(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` with ``text`` in its bottom right corner (PIL's default font)."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8))
    draw = ImageDraw.Draw(im)
    left, top, right, bottom = draw.textbbox((0, 0), text)
    draw.text((im.width - (right - left) - 8, im.height - (bottom - top) - 8), text, fill=(20, 20, 120))
    return np.asarray(im)
