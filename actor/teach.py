"""HIL-SERL's prior data and safety box (``--recipe hil-serl``, :mod:`khgrl.common.config.hilserl`): successful
demonstrations recorded by the task's scripted teacher in the scenes the run will see, and the box around them.

**The teacher** (``[hilserl] teacher_demos`` N > 0, ``--method hil-serl``): before the first episode the actor
drives the robot under its delta control with the task's scripted human taking it over for the whole episode --
the task's ``scripted_human.takeover`` (or ``scripted_human``) where it helps, the step's KMP mean elsewhere
(:class:`~khgrl.common.tasks.scripted_human.WholeEpisode`) -- in the scenes of the run's episodes 1, 2, ...
(``reset_episode(k)``: a varying scene is the one episode k will have), and keeps an episode only if it succeeds,
until N are kept or ``teacher_tries`` episodes were tried (HIL-SERL's ``record_demos.py`` keeps the successful
teleoperated episodes until it has 20). Only the run's first actor sends them, as intervened transitions on its
stream (the learner's prior data, :mod:`khgrl.learner.replay`), instead of replaying the task's demonstrations
(:mod:`khgrl.actor.demos`); they are not episodes. What the teacher did is in ``actor-ID/teacher.json`` and the
actor's ``summary.json`` (``teacher``: tries, kept, steps sent, steps driven in all tries -- a person's time;
``demo_transitions``).

**The task-sized box** (``[hilserl] safety_box task``): the delta actions are clipped to the bounding box of the
positions the kept demonstrations visited (none kept, or no teacher: the task's demonstrations), widened on each
side by ``box_margin`` of the workspace's extent and kept inside the workspace. Every actor computes it (an actor
other than the first runs the teacher without sending); ``teacher.json`` keeps it for a resumed actor.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from khgrl.actor.demos import FIRST_ACTOR
from khgrl.common.delivery.vouching import DEMO
from khgrl.common.tasks.api import TaskError
from khgrl.common.tasks.scripted_human import WholeEpisode

__all__ = ["TEACHER_FILE", "teacher", "teach", "task_box", "prepare"]

log = logging.getLogger("khgrl.actor")
TEACHER_FILE = "teacher.json"


def teacher(task: Any) -> WholeEpisode:
    """The task's scripted teacher: its scripted human taking the robot over for whole episodes.

    :param task: the task (:class:`~khgrl.common.tasks.api.Task`)
    :raises TaskError: the task has no scripted human
    """
    guide = getattr(task, "scripted_human", None)
    if guide is None:
        raise TaskError(f"task {task.name!r} has no scripted_human to record demonstrations with (--teacher-demos)")
    return WholeEpisode(getattr(guide, "takeover", guide))


def task_box(points: np.ndarray, low: np.ndarray, high: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box of ``points`` widened by ``margin`` x the workspace's extent, inside the workspace.

    :param points: (K, O) positions
    :param low: the workspace's lower corner
    :param high: its upper corner
    :param margin: the fraction of the workspace's extent added on each side
    """
    pts = np.asarray(points, np.float64).reshape(-1, np.size(low))
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    pad = margin * (high - low)
    return np.clip(pts.min(axis=0) - pad, low, high), np.clip(pts.max(axis=0) + pad, low, high)


def _episode(loop: Any, guide: WholeEpisode, episode: int) -> tuple[list, list, bool] | None:
    """One teacher episode in the scene of the run's ``episode``: (transitions, positions, success); None if the
    actor was stopped on the way."""
    env = loop.p.env
    obs, _ = env.reset_episode(episode)
    rest = np.zeros(env.action_space.shape, dtype=np.float32)  # (ignored: the takeover drives)
    transitions, positions, success, done = [], [env.position.copy()], False, False
    while not done:
        loop.service()
        loop.rate_limit()
        if loop.flag:
            env.set_correction(None)
            return None
        t = min(env.t, env.horizon - 1)
        env.set_correction(guide(env.mapping.mean(t), step=t, phase=float(env.mapping.phases[t]),
                                 position=env.position.copy(), obs=env.inner_obs))
        next_obs, reward, terminated, truncated, info = env.step(rest)
        transitions.append((obs, next_obs, info["action"], reward, terminated, truncated, bool(info["clipped"])))
        positions.append(env.position.copy())
        success = success or bool(info["success"])
        done, obs = terminated or truncated, next_obs
    env.set_correction(None)
    return transitions, positions, success


def _send(loop: Any, transitions: list) -> None:
    """One kept demonstration as intervened transitions on the actor's stream, cut as an episode's are."""
    stream = loop.p.stream
    for obs, next_obs, action, reward, terminated, truncated, clipped in transitions:
        stream.add(obs, next_obs, action, reward, terminated, truncated, True, clipped, DEMO)  # (a0's first rows)
        if terminated or truncated or stream.count % loop.cfg.stream.batch == 0:
            stream.cut()


def teach(loop: Any) -> dict | None:
    """The teacher's episodes (module docstring); the first actor sends the kept ones. Returns what it did
    (``tries``, ``kept``, ``steps`` sent, ``steps_driven`` in all tries, ``positions`` visited by the kept ones),
    None if stopped on the way.

    :param loop: the actor's :class:`~khgrl.actor.loop.ActorLoop`
    """
    hs, env = loop.cfg.hilserl, loop.p.env
    guide = teacher(env.task)
    send = loop.id == FIRST_ACTOR and loop.p.stream.count == 0
    tries, kept, steps, driven, positions = 0, 0, 0, 0, []
    while kept < hs.teacher_demos and tries < hs.tries:
        tries += 1
        got = _episode(loop, guide, tries)
        if got is None:
            return None
        transitions, visited, success = got
        driven += len(transitions)  # a person's steps, kept or not (the human budget)
        if success:
            kept, positions = kept + 1, positions + visited
            if send:
                _send(loop, transitions)
                steps += len(transitions)
    log.info("actor %s: the teacher kept %d successful demonstrations of %d tries (%d prior transitions sent)",
             loop.id, kept, tries, steps)
    return {"tries": tries, "kept": kept, "steps": steps, "steps_driven": driven, "sent": send,
            "positions": positions}


def prepare(loop: Any) -> int:
    """Before the first episode of a ``--method hil-serl`` actor: the teacher (``teacher_demos`` > 0, not on a
    resumed actor) and the safety box (``safety_box task``); writes ``teacher.json``. Returns the prior transitions
    sent (0 without a teacher, or stopped).

    :param loop: the actor's :class:`~khgrl.actor.loop.ActorLoop`
    """
    cfg, env = loop.cfg, loop.p.env
    if cfg.method != "hil-serl" or env.delta is None:
        return 0
    path = Path(cfg.run_dir) / f"actor-{loop.id}" / TEACHER_FILE
    if loop.episode > 0 and path.is_file():  # a resumed actor: its box as it was
        record = json.loads(path.read_text())
    else:
        record = {"tries": 0, "kept": 0, "steps": 0, "steps_driven": 0, "sent": False}
        taught = teach(loop) if cfg.hilserl.teacher_demos > 0 else record
        if taught is None:
            return 0
        record = {**taught, "box": None}
        points = taught.pop("positions", None) or np.asarray(env.world.demos).reshape(-1, env.world.out_dim)
        record.pop("positions", None)
        if cfg.hilserl.safety_box == "task":
            low, high = task_box(np.asarray(points), env.world.low, env.world.high, cfg.hilserl.box_margin)
            record["box"] = [low.tolist(), high.tolist()]
        path.write_text(json.dumps(record, indent=1))
    if record.get("box"):
        env.delta = dataclasses.replace(env.delta, low=np.asarray(record["box"][0]), high=np.asarray(record["box"][1]))
        log.info("actor %s: the safety box is the task's, %s to %s", loop.id, record["box"][0], record["box"][1])
    loop.teacher = {k: record.get(k) for k in ("tries", "kept", "steps", "steps_driven", "box")}
    return int(record["steps"]) if record.get("sent") and loop.episode == 0 else 0
