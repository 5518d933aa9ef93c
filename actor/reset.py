"""Between two episodes (README, "On a real robot"): the robot returns to the start along a rate-limited path
(``--reset-path``; on in robot mode), then, with ``--confirm-reset``, it is held until a person says it is ready
(``khgrl ready RUN_DIR``, or r in a human client's window); the reset itself waits while the actor is held (the
e-stop, no supervisor yet: :mod:`khgrl.actor.supervision`). The path is paced at ``--rate``, and the e-stop, pauses
and the watchdog hold it as they hold an episode's steps; it is not a transition (no reward, nothing stored).

The path starts from the position last sent at the velocity of the episode's last step, and slows down within the
limits before it turns back (:func:`khgrl.common.tasks.motion.reset_path`). A process's first episode has none: the
task environment's own ``reset`` puts the robot at its start then (a real robot's adapter reads where it is). The
e-stop pressed on the path, or while the robot waits for ready, holds the task's reset too.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

__all__ = ["reset_phase"]

log = logging.getLogger("khgrl.actor")


def reset_phase(loop: Any, episode: int) -> bool:
    """Before ``episode``: the path back to the start (not before the process's first episode), then the wait for
    ready; False if the actor is to stop.

    :param loop: the :class:`~khgrl.actor.loop.ActorLoop` (its env, pacing, watchdog and settings).
    :param episode: the episode about to start.
    """
    s, env = loop.cfg.safety, loop.p.env
    limits = s.path(loop.cfg.stream.mode)
    if limits is not None and episode > loop.first_episode:
        steps, largest, last, path = 0, 0.0, env.desired.copy(), env.reset_path(limits)
        while True:
            if not loop.before_step():  # paced; the e-stop, a pause or the learner hold the path too
                return False
            p = next(path, None)
            if p is None:
                break
            largest, last, steps = max(largest, float(np.max(np.abs(p - last)))), p, steps + 1
        loop.watchdog.paths.append({"episode": episode, "steps": steps, "max_step": largest})
        log.info("reset path before episode %d: %d steps back to the start (largest step %.4g)", episode, steps,
                 largest)
    if s.confirm_reset:
        loop.inbound.awaiting_ready = episode
    if loop.inbound.paused:  # no reset (a real robot's moves to its start) under the e-stop or without supervision
        loop.rate_limit()  # held (the watchdog says why) until ready, the e-stop released, or stopped
    return not loop.flag
