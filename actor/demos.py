"""The demonstrations as transitions: prior data for RLPD sampling (``--sampling rlpd``, and ``--method hil-serl``).

HIL-SERL and RLPD put demonstrations into a prior-data buffer as transitions, rewards included. Here the actor
replays each demonstration through its environment before its first episode, as a human correction that follows
it: at step t the correction is the demonstration's grid point t, so the stored action is the one that produces
it under the run's control -- eq. 6's a_h for KGRL and KhGRL, the takeover action for HIL-SERL's delta control --
and the reward is the environment's. The transitions go out on the actor's own stream flagged ``intervened`` (the
learner's prior data are exactly its intervened transitions), under the same flow control as an episode, so none is
lost or duplicated. They are not episodes: episodes.csv, corrections.csv and the frames do not show them; the
actor's log and ``summary.json`` (``demo_transitions``) count them.

Only the run's first actor (``a0``) replays them, once, when its stream starts empty; a task whose scene changes
every episode replays them in the scene of episode 0 (``scene_seed(seed, 0)``), not in the scene they were
recorded in.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from khgrl.common.delivery.vouching import DEMO

__all__ = ["replay_demos", "replays_demos"]

log = logging.getLogger("khgrl.actor")

FIRST_ACTOR = "a0"


def replays_demos(loop: Any) -> bool:
    """Whether this actor replays the demonstrations now: sampling is rlpd, it is the run's first actor, its
    stream and episodes are empty (a restarted actor has sent them already), and no teacher records others."""
    p = loop.p
    teacher = loop.cfg.method == "hil-serl" and loop.cfg.hilserl.teacher_demos > 0  # (actor/teach.py's instead)
    return (loop.cfg.tqc.sampling == "rlpd" and loop.id == FIRST_ACTOR and loop.episode == 0
            and p.stream.count == 0 and not teacher)


def replay_demos(loop: Any) -> int:
    """Replay every demonstration as intervened transitions on the actor's stream (see the module docstring);
    returns how many were sent (0 where :func:`replays_demos` says no, or stopped on the way).

    :param loop: the actor's :class:`~khgrl.actor.loop.ActorLoop` (its parts, flow control and stop flag)
    """
    if not replays_demos(loop):
        return 0
    p, env = loop.p, loop.p.env
    demos = np.asarray(env.world.demos, dtype=np.float64)
    rest = np.zeros(env.action_space.shape, dtype=np.float32)  # (ignored: the correction drives)
    sent, successes = 0, 0
    for demo in demos:
        obs, _ = env.reset_episode(0)
        done, success = False, False
        while not done:
            loop.service()
            loop.rate_limit()
            if loop.flag:
                env.set_correction(None)
                return sent
            env.set_correction(demo[min(env.t, len(demo) - 1)])
            next_obs, reward, terminated, truncated, info = env.step(rest)
            p.stream.add(obs, next_obs, info["action"], reward, terminated, truncated, True, bool(info["clipped"]),
                         DEMO)  # (the run's own: the learner takes them as prior data from a0's first rows)
            sent += 1
            success = success or bool(info["success"])
            done = terminated or truncated
            if done or p.stream.count % loop.cfg.stream.batch == 0:
                p.stream.cut()
            obs = next_obs
        successes += int(success)
    env.set_correction(None)
    log.info("actor %s: %d demonstrations replayed as %d prior transitions (%d reached success)", loop.id,
             len(demos), sent, successes)
    return sent
