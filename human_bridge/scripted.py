"""The scripted human: a reproducible stand-in for a person who drags the robot's desired position.

In the given episodes it asks the task's ``scripted_human`` (:class:`khgrl.common.tasks.api.Task`) for P_h at each
step's
KMP mean; optional seeded noise imitates an unsteady hand; None releases. The passage world's
(:class:`khgrl.common.tasks.passage.task.PassageGuide`) knows a safe path through the gaps (and around the obstacle) --
the
scenario's ``human_waypoints`` -- and, over the part of the task where help is needed (the scenario's
``human_window``, in workspace x), sets P_h on that path at the point the KMP mean has reached in x.

Its output is a correction P_h or ``None`` (released) per step: exactly what a person's drag produces.
The decision (:class:`ScriptedHuman`) and its single-process use (:class:`HumanCorrectionWrapper`, applied with
``set_correction``) are in :mod:`khgrl.common.tasks.scripted_human`, shared with the single-process reference; in the
distributed system ``khgrl human scripted`` (:func:`run`, :class:`ScriptedAnswers`) publishes it as
step-addressed correction messages that the actor applies the same way.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from khgrl.common.config.process import ProcessConfig
from khgrl.common.config.settings import PAPER_EPISODES
from khgrl.common.process import StopFlag, install_stop_handlers
from khgrl.common.tasks.api import TaskError, load_task
from khgrl.common.tasks.scripted_human import HumanCorrectionWrapper, ScriptedHuman, ScriptedHumanConfig
from khgrl.common.wire.protocol import Frame
from khgrl.human_bridge.client import CorrectionPublisher, connected

__all__ = ["PAPER_EPISODES", "ScriptedHuman", "ScriptedHumanConfig", "HumanCorrectionWrapper", "ScriptedAnswers",
           "add_arguments", "run"]


# ------------------------------------------------------------------------------------ the scripted client
class ScriptedAnswers:
    """The scripted client's answer to each frame (lock-step, docs/distributed_runs.md).

    The frame describes step t. In a help episode it answers with a step-addressed correction for step t + 1
    (P_h from the KMP mean there): the actor waits for it, so latency does not shift P_h against the mean.
    Other episodes: nothing (a hold left over is released). While the episode before a help episode runs, it
    announces lock-step for that episode with its word for step 0.

    :param human: the scripted human that decides P_h.
    :param pub: the correction stream to publish on.
    """

    def __init__(self, human: ScriptedHuman, pub: CorrectionPublisher) -> None:
        self.human = human
        self.pub = pub
        self.means: dict[int, np.ndarray] = {}  # step -> KMP mean, from the frames seen (the same every episode)
        self.announced: set[tuple[str, int]] = set()  # (actor, episode) whose lock-step was announced

    def frame(self, f: Frame) -> None:
        """Answer one frame.

        :param f: the actor's frame of step ``f.t``.
        """
        ep, t, actor = f.episode, f.t, f.actor
        self.means.setdefault(t, f.mean)
        if self.human.active_in(ep) and f.next_mean is not None:
            self.pub.send(actor, self.human.correction(ep, f.next_mean), ep, t, step=t + 1)
        elif self.pub.active.get(actor, False):
            self.pub.send(actor, None, ep, t)
        if self.human.active_in(ep + 1) and (actor, ep + 1) not in self.announced:
            self.announced.add((actor, ep + 1))
            p0 = self.human.correction(ep + 1, self.means[0]) if 0 in self.means else None
            self.pub.send(actor, p0, ep + 1, t, step=0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The scripted client's own flags (its settings -- scenario, seed, episodes, noise -- are run settings)."""
    parser.add_argument("--actor", default="*", help="actor id to drive (default: %(default)s, every actor)")
    parser.add_argument("--id", default="scripted", help="client id (default: %(default)s)")


def run(args: argparse.Namespace, proc: ProcessConfig) -> int:
    """``khgrl human scripted``: corrections along the safe path in the run's ``human_episodes``.

    :param args: the parsed command line (:func:`add_arguments`).
    :param proc: the resolved run settings (run id, endpoint, scenario, seed, human_episodes, human_noise).
    """
    cfg = proc.cfg
    try:
        task = load_task(cfg.task_spec, cfg.demos or None)
    except TaskError as exc:
        print(f"khgrl human scripted: error: {exc}", file=sys.stderr, flush=True)
        return 2
    if task.scripted_human is None:
        print(f"khgrl human scripted: error: task {task.name!r} has no scripted_human: use --human gui or none",
              file=sys.stderr, flush=True)
        return 2
    human = ScriptedHuman(task.scripted_human, ScriptedHumanConfig(episodes=tuple(cfg.human_episodes),
                                                                   noise=cfg.human_noise, seed=cfg.seed))
    flag = StopFlag()
    install_stop_handlers(flag)
    print(f"khgrl human scripted ({args.id}) driving actor {args.actor} of run {proc.run} in episodes "
          f"{list(cfg.human_episodes)}", flush=True)
    try:
        with connected(proc, args.id, flag, args.actor) as link:
            answers = ScriptedAnswers(human, link.pub)
            while not flag:
                got = link.next(timeout=0.2)
                if got is not None:
                    answers.frame(got[1])
                link.publish_status()
    except ConnectionError as exc:
        if flag:
            return 0
        print(f"khgrl human scripted: {exc}", file=sys.stderr, flush=True)
        return 1
    print(f"khgrl human scripted: {link.frames} frames seen, {link.pub.sent} correction messages sent, "
          f"{link.rejects.total} rejected", flush=True)
    return 0
