"""The actor's physical corrections (``--physical detect|scripted``; :mod:`khgrl.common.tasks.physical`): a push on
the arm, seen in its measured position, becomes the human's P_h -- the arm's own position, step after step, through
eq. 6, flagged intervened, recorded in corrections.csv with ``source`` ``physical``, and the exploration scale L
refits from it as from a drag. A hand on the robot wins over a remote client's drag while it lasts.

With ``scripted`` (simulation), a scripted physical human pushes the arm in the human's episodes
(``--human-episodes``): the task's scripted human says where to (as it would drag), and the task's ``push`` hook
applies a force towards it (Panda: MuJoCo's ``xfrc_applied``). The detector sees only positions. Each step of every
episode goes into ``RUN_DIR/actor-ID/physical.csv`` (episode, step, pushed, detected) to measure detection against
the pushes (:func:`detection`).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
from khgrl.common.tasks.api import TaskError
from khgrl.common.tasks.physical import PhysicalDetector

__all__ = ["PhysicalHands", "detection", "SOURCE"]

SOURCE = "physical"  # corrections.csv's client and source of a physical correction


class PhysicalHands:
    """Detection of physical interaction and, in simulation, the scripted physical human (module docstring).

    :param env: the actor's :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
    :param mode: ``detect`` or ``scripted``.
    :param human: the scripted human deciding where to push (``scripted``; its episodes are the human's).
    :param out_dir: where ``physical.csv`` goes (appended to when it exists: a resumed actor).
    """

    def __init__(self, env: Any, mode: str, human: Any = None, out_dir: Path | None = None) -> None:
        self.on = mode != "off"
        self.pushed, self.counts = False, {"pushed_steps": 0, "detected_steps": 0, "interactions": 0}
        self._fh = None
        if not self.on:
            return
        if mode == "scripted" and env.task.push is None:
            raise TaskError(f"task {env.task.name!r} has no push hook: --physical scripted needs a robot that can "
                            f"be pushed in simulation (e.g. panda:pick); --physical detect watches a real one")
        self.env, self.human = env, human if mode == "scripted" else None
        self.detector = PhysicalDetector.from_demos(env.world.demos)
        if out_dir is not None:
            path = Path(out_dir) / "physical.csv"
            new = not path.is_file() or path.stat().st_size == 0
            self._fh = open(path, "a", newline="")
            self._w = csv.writer(self._fh)
            if new:
                self._w.writerow(("episode", "step", "pushed", "detected", "deviation", "motion", "contact"))

    @classmethod
    def off(cls) -> PhysicalHands:
        """No physical corrections (``--physical off``): every method does nothing."""
        return cls(None, "off")

    def correction(self, episode: int, p_h: np.ndarray | None) -> tuple[np.ndarray | None, bool]:
        """Before a step: push (scripted), and the P_h that applies -- the arm's position while an interaction
        lasts, else the remote client's ``p_h``; (P_h, whether it is physical).

        :param episode: the episode.
        :param p_h: the arbiter's P_h (None: no remote correction).
        """
        if not self.on:
            return p_h, False
        env = self.env
        if self.human is not None:
            target = None
            if self.human.active_in(episode) and env.t < env.horizon:
                target = self.human.correction(episode, env.mapping.mean(env.t), step=env.t, phase=env.phase,
                                               position=env.position, obs=env.inner_obs)
            env.task.push(env.inner, target)
            self.pushed = target is not None
        if self.detector.active:
            return env.position.copy(), True
        return p_h, False

    def observe(self, episode: int, t: int, before: np.ndarray, info: dict) -> None:
        """After a step: the detector's update and the log row.

        :param episode: the episode.
        :param t: the step.
        :param before: the measured position before the step.
        :param info: the step's info (``desired``: the position sent).
        """
        if not self.on:
            return
        was, task = self.detector.active, self.env.task
        contact = bool(task.contact(self.env.inner)) if task.contact is not None else False
        now = self.detector.update(info["desired"], before, self.env.position, contact)
        self.counts["interactions"] += int(now and not was)
        self.counts["pushed_steps"] += int(self.pushed)
        self.counts["detected_steps"] += int(now)
        if self._fh is not None:
            dev, motion = self.detector.last
            self._w.writerow((episode, t, int(self.pushed), int(now), f"{dev:.5g}", f"{motion:.5g}", int(contact)))

    def end_episode(self) -> None:
        """The episode ended: the hand lets go, the detector starts afresh."""
        if not self.on:
            return
        if self.human is not None:
            self.env.task.push(self.env.inner, None)
        self.pushed = False
        self.detector.reset()
        if self._fh is not None:
            self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()


def detection(rows: list[dict]) -> dict:
    """Per-step precision and recall of the detected steps against the pushed ones (also over the pushed steps without
    contact), the delay in steps from a push's first step to its detection, and the detected steps in episodes
    without a push.

    :param rows: ``physical.csv``'s rows (``episode``, ``step``, ``pushed``, ``detected``).
    """
    pushed = np.array([int(r["pushed"]) for r in rows], bool)
    found = np.array([int(r["detected"]) for r in rows], bool)
    episodes = np.array([int(r["episode"]) for r in rows])
    tp = int(np.sum(pushed & found))
    delays, start = [], None
    for i in range(len(rows)):
        if pushed[i] and (i == 0 or not pushed[i - 1] or episodes[i] != episodes[i - 1]):
            start = i
        if start is not None and found[i]:
            delays.append(i - start)
            start = None
        if start is not None and (not pushed[i] or (i + 1 < len(rows) and episodes[i + 1] != episodes[i])):
            start = None  # the push ended undetected
    free = np.array([not int(r.get("contact") or 0) for r in rows], bool)  # (no contact column: all free)
    quiet = [e for e in np.unique(episodes) if not pushed[episodes == e].any()]
    return {"steps": len(rows), "pushed": int(pushed.sum()), "detected": int(found.sum()),
            "precision": tp / found.sum() if found.any() else None,
            "recall": tp / pushed.sum() if pushed.any() else None, "delay_steps": delays,
            "recall_without_contact": int(np.sum(pushed & found & free)) / int(np.sum(pushed & free))
            if np.any(pushed & free) else None,
            "false_in_quiet_episodes": int(sum(found[episodes == e].sum() for e in quiet)),
            "quiet_episodes": len(quiet)}
