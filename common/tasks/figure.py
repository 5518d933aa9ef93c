"""The picture of a task that the documentation shows (README: the passage world's two scenarios):

    python -m khgrl.common.tasks.figure passage:high_cov --steps 175 --out docs/passage_high_cov.png
    python -m khgrl.common.tasks.figure passage:low_cov --steps 235 --out docs/passage_low_cov.png

The task's environment (:class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`) follows the KMP mean (zero action, eq. 5)
with the task's scripted human correcting where it helps (eq. 6), for ``--steps`` steps; the frame after them is
drawn by :class:`~khgrl.common.tasks.render.TaskRenderer`, the renderer of every task, with its legend.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

__all__ = ["task_figure", "main"]


def task_figure(spec: str, steps: int, size: tuple[int, int] = (600, 660)) -> np.ndarray:
    """(H, W, 3) uint8 image of task ``spec`` after ``steps`` steps along the KMP mean with its scripted human.

    :param spec: a task spec (``passage:high_cov``, ``package.module:callable``).
    :param steps: steps to take before drawing (stops early at the episode's end).
    :param size: (W, H) of the image in pixels.
    """
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.kgrl_env import KGRLEnv
    from khgrl.common.tasks.render import TaskRenderer, frame_from_env

    env = KGRLEnv(load_task(spec))
    env.reset()
    human = env.task.scripted_human
    zero = np.zeros(env.world.out_dim)
    for _ in range(steps):
        env.set_correction(human(env.mapping.mean(env.t)) if human is not None else None)
        _, _, term, trunc, _ = env.step(zero)
        if term or trunc:
            break
    renderer = TaskRenderer(env.descriptor(spec), size, strip_height=60, legend=True)
    return renderer.render_rgb(frame_from_env(env))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m khgrl.common.tasks.figure", description=__doc__.split("\n\n")[0])
    p.add_argument("task", help="task spec, e.g. passage:high_cov")
    p.add_argument("--steps", type=int, default=175, help="steps before the frame is drawn (default: %(default)s)")
    p.add_argument("--size", type=int, nargs=2, default=[600, 660], metavar=("W", "H"),
                   help="image size in pixels (default: 600 660)")
    p.add_argument("--out", required=True, help="PNG to write (required)")
    args = p.parse_args(argv)
    img = task_figure(args.task, args.steps, tuple(args.size))
    import pygame

    pygame.image.save(pygame.surfarray.make_surface(img.swapaxes(0, 1)), args.out)
    print(f"wrote {args.out} ({img.shape[1]}x{img.shape[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
