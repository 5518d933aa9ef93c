"""The position sent to the robot between two control steps (README, "On a real robot"): a hold, and the path back to
the start between episodes.

* **A hold** (:meth:`~khgrl.common.tasks.kgrl_env.KGRLEnv.hold`: the e-stop, a pause, a wait for ready or for the
  learner, a silent human, a stalled control loop) stops the robot: the task's ``hold`` adapter gets the position
  last sent, and when it answers with the environment's observation (the robot measured while held,
  :func:`measured`) that is where the robot is now. After any hold the rate limits restart *at rest* from that
  measured position: the first step is at most one acceleration step, and an arm moved by hand while held is not
  commanded back. Without a measurement they restart from the position last sent (a position-controlled arm gets
  there while held; the last step's observation is older than that).
* **The path back to the start** (:func:`reset_path`) goes on from the episode's last step at its velocity and slows
  down within the limits before it turns back along the trail.
"""

from __future__ import annotations

from typing import Any, Iterator

import numpy as np
from khgrl.common.tasks.api import TaskError
from khgrl.common.tasks.safety import RateLimiter

__all__ = ["measured", "reset_path"]


def measured(env: Any, obs: Any) -> np.ndarray:
    """The task environment's observation ``obs`` that the ``hold`` adapter returned, checked (the observation
    space's shape, finite); the robot's position in it becomes ``env.position``.

    :param env: the :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
    :param obs: what ``hold(env, p_t)`` returned.
    :raises TaskError: naming what is wrong with it.
    """
    shape = env.inner.observation_space.shape
    try:
        o = np.asarray(obs, dtype=np.float64)
    except (TypeError, ValueError):
        o = np.full(1, np.nan)
    if o.shape != tuple(shape) or not np.all(np.isfinite(o)):
        raise TaskError(f"task {env.task.name!r}: hold(env, p_t) must return None or a finite observation of shape "
                        f"{tuple(shape)}, got {obs!r}")
    return o


def reset_path(env: Any, limits: tuple[float, float], max_steps: int = 10_000) -> Iterator[np.ndarray]:
    """Drive the robot back to the start -- the KMP mean at phase 0 -- along the way it came (its trail in reverse: a
    path it has been on, not a straight line through what it went around), within ``limits`` (a
    :class:`~khgrl.common.tasks.safety.RateLimiter` that goes on from the last step sent, at its velocity), stepping
    the task's environment with each position (no transition, no reward); yields each position sent, until it is at
    the start at rest. A hold on the way restarts it at rest from where the robot is measured
    (:meth:`~khgrl.common.tasks.kgrl_env.KGRLEnv.hold`).

    :param env: the :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
    :param limits: ``(max_speed, max_accel)`` in units of the demonstrations' largest step.
    :param max_steps: a bound on the path's length.
    """
    world = env.world
    start = np.asarray(world.model.grid_mean[0], dtype=np.float64)
    lim = RateLimiter.from_demos(world.demos, *limits, world.low, world.high)
    lim.reset(env.anchor, env.sent_step)
    env.path_limiter = lim
    waypoints = [*reversed(env.trail), start]
    k = 0
    try:
        for _ in range(max_steps):
            while k < len(waypoints) - 1 and np.max(np.abs(waypoints[k] - lim.last)) <= lim.speed:
                k += 1  # the next point of the trail not within a step
            p = lim.limit(waypoints[k])[0]
            inner_obs = env.inner.step(p if env.task.command is None else env.task.command(env.inner, p))[0]
            env.sent(p, inner_obs)
            yield p
            if k == len(waypoints) - 1 and np.max(np.abs(p - start)) <= 1e-9 and not np.any(lim.velocity):
                return
    finally:
        env.path_limiter = None
