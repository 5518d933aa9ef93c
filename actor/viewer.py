"""The actor's live view in Rerun (``khgrl up --view rerun|rerun:FILE.rrd|rerun:web``): a
:class:`~khgrl.common.step_records.StepRecord` listener that logs every step of the episode as it happens through
:class:`~khgrl.common.rerun_log.RunLogger` (the entities and timelines are listed there), plus the simulator's camera
image every K steps where the task's environment has one (``camera_frame(size)``: Fetch, gym-hil's Panda).

The launcher tells its children where to log in ``$KHGRL_VIEW`` (:class:`~khgrl.common.rerun_log.ViewTarget`);
without it the actor imports nothing of Rerun. Logging never stops the robot: Rerun's SDK batches and sends in its
own threads, and an exception in a logging call is logged once and turns the view off (the camera alone, if it is
the camera that fails); nothing here draws a random number or touches the environment's state, so a seeded run's
episodes are the same with and without a view.
"""

from __future__ import annotations

import logging
from typing import Any, Callable

import numpy as np
from khgrl.common.rerun_log import RunLogger, ViewTarget, blueprint, open_recording
from khgrl.common.step_records import IMAGE

__all__ = ["LiveView", "live_listeners"]

log = logging.getLogger("khgrl.actor")
FLUSH_S = 3.0  # at the end: how long the actor waits for its last data to reach the sink


class LiveView:
    """Logs an actor's episodes into the run's Rerun recording as they happen.

    :param target: where to log (the launcher's sink or viewer) and the camera settings.
    :param run_id: the run id (the recording id).
    :param actor: this actor's id.
    :param env: the actor's :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` (its world, and its camera if any).
    :param version: returns the policy weights version the actor acts with now.
    """

    def __init__(self, target: ViewTarget, run_id: str, actor: str, env: Any,
                 version: Callable[[], int] | None = None) -> None:
        self.target, self.env, self.version = target, env, version
        self.on = True
        self.logger = RunLogger(open_recording(run_id, url=target.url), actor)
        camera = getattr(getattr(env, "inner", None), "camera_frame", None)
        self.camera = camera if callable(camera) and target.camera_every > 0 else None
        self._projector: np.ndarray | None = None
        if self.camera is not None:  # the renderer is made here (a first image takes ~0.3 s), not in the loop's step
            self._render()
        w = env.world
        self._guard(self.logger.scene, w.demos, (w.low, w.high), tuple(w.view.shapes))
        layout = getattr(env, "cameras", None)  # a camera task's images (what the policy sees)
        self.images = tuple(layout.images) if layout is not None and target.camera_every > 0 else ()
        if target.actors and target.actors[0] == actor:  # one actor sends the layout (it knows of a camera)
            self._guard(self.logger.rec.send_blueprint, blueprint(list(target.actors), self.camera is not None,
                                                                  self.images))

    def _guard(self, fn: Callable, *args: Any) -> None:
        if not self.on:
            return
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - a viewer must never stop the robot
            self.on = False
            log.warning("Rerun view off after an error in %s: %r", getattr(fn, "__name__", fn), exc)

    def start(self, episode: int, scene: dict[str, np.ndarray]) -> None:
        """:class:`~khgrl.common.step_records.StepRecord` listener: an episode begins."""
        self._projector = scene["kmp_projector"]
        self._guard(self.logger.start, episode, scene)

    def step(self, episode: int, row: dict[str, Any]) -> None:
        """A step was taken (and, every ``camera_every`` steps, the camera's image and a camera task's images)."""
        if not self.on or self._projector is None:
            return
        t = int(row["t"])
        self._guard(self.logger.step, episode, row, self._projector[min(t, len(self._projector) - 1)])
        if self.camera is not None and t % self.target.camera_every == 0:
            self._image(episode, t)
        if self.images and t % self.target.camera_every == 0:
            for key in self.images:
                self._guard(self.logger.image, episode, t, row[IMAGE + key], 80, f"images/{key}")

    def _render(self) -> np.ndarray | None:
        try:
            return self.camera(self.target.camera_size)
        except Exception as exc:  # noqa: BLE001 - e.g. no offscreen OpenGL here: the rest of the view goes on
            self.camera = None
            log.warning("Rerun view: no camera images (%r); set MUJOCO_GL=egl or osmesa for offscreen rendering", exc)
            return None

    def _image(self, episode: int, t: int) -> None:
        rgb = self._render()
        if rgb is not None:
            self._guard(self.logger.image, episode, t, rgb)

    def finish(self, episode: int, arrays: dict[str, np.ndarray], stats: Any) -> None:
        """The episode finished: its band, return, success and the weights version."""
        self._guard(self._finish, episode, arrays, stats)

    def _finish(self, episode: int, arrays: dict[str, np.ndarray], stats: Any) -> None:
        version = self.version() if self.version is not None else None
        self.logger.finish(episode, arrays, float(stats.ret), bool(stats.success), version)

    def close(self) -> None:
        """Send what is left (up to :data:`FLUSH_S`) and disconnect."""
        rec, self.on = self.logger.rec, False
        try:
            rec.flush(timeout_sec=FLUSH_S)
            rec.disconnect()  # (blocks until the gRPC sink has what was logged)
        except Exception as exc:  # noqa: BLE001
            log.warning("Rerun view: the last data may be lost (%r)", exc)


def live_listeners(run_id: str, actor: str, env: Any, version: Callable[[], int] | None = None) -> tuple:
    """The actor's step listeners: a :class:`LiveView` when ``$KHGRL_VIEW`` names a target, else none. A view that
    cannot start (no Rerun SDK, a bad target) is one warning and no view.

    :param run_id: the run id.
    :param actor: this actor's id.
    :param env: the actor's environment.
    :param version: the weights version now.
    """
    try:
        target = ViewTarget.from_env()
        if target is None:
            return ()
        return (LiveView(target, run_id, actor, env, version),)
    except Exception as exc:  # noqa: BLE001 - no view is better than no robot
        log.warning("no Rerun view: %s", exc)
        return ()
