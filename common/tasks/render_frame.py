"""What a :class:`~khgrl.common.tasks.render.TaskRenderer` draws of one moment: :class:`TaskFrame`, and
:func:`frame_from_env`, the current frame of a :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` (for a varying-scene
task, with its episode's adapted KMP mean and via-points: :mod:`khgrl.common.tasks.scene_frame`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from khgrl.common.tasks.scene_frame import scene_arrays

__all__ = ["TaskFrame", "frame_from_env"]


@dataclass
class TaskFrame:
    """What changes from frame to frame, in command coordinates (O outputs).

    :param position: (O,) where the robot is.
    :param desired: (O,) the desired position P_t.
    :param phase: s in [0, 1].
    :param t: the step index.
    :param trail: (k, O) the robot's positions so far this episode, or None.
    :param band: (N, 2, O) the exploration band [low, high] per grid point, or None.
    :param correction: (O,) the human's P_h while intervening, or None.
    :param human_active: a human is intervening (orange frame, badge).
    :param text: status lines for the bottom strip.
    :param mean: (N, O) the episode's adapted KMP mean, or None (the descriptor's mean).
    :param via: (V, 1 + O) the episode's via-points, [phase, position...] per row, or None.
    """

    position: np.ndarray
    desired: np.ndarray
    phase: float = 0.0
    t: int = 0
    trail: np.ndarray | None = None
    band: np.ndarray | None = None
    correction: np.ndarray | None = None
    human_active: bool = False
    text: list[str] = field(default_factory=list)
    mean: np.ndarray | None = None
    via: np.ndarray | None = None


def frame_from_env(env: Any, text: list[str] | None = None) -> TaskFrame:
    """The current frame of a :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` (robot, P_t, phase, trail, band,
    correction; for a varying-scene task whose KMP the reset adapted, the episode's adapted mean and via-points:
    a renderer made from the task's descriptor draws each episode's scene without being told).

    :param env: a KGRLEnv (or subclass, e.g. PassageEnv).
    :param text: strip lines (default: task name, step, phase, whether a human intervenes).
    """
    mapping = env.mapping
    correction = getattr(env, "correction", None)
    scene = scene_arrays(env)
    if text is None:
        text = [f"{env.task.name}  t={env.t:3d}/{env.horizon}  s={env.phase:.2f}",
                "human: " + ("intervening" if correction is not None else "-")]
    return TaskFrame(position=np.array(env.position, np.float64), desired=np.array(env.desired, np.float64),
                     phase=float(env.phase), t=int(env.t), trail=np.array(env.trail, np.float64),
                     band=mapping.band() if mapping.scale_table is not None else None,
                     correction=None if correction is None else np.array(correction, np.float64),
                     human_active=correction is not None, text=list(text),
                     mean=None if scene is None else scene.mean, via=None if scene is None else scene.via)
