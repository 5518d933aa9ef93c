"""The scripted human: a reproducible stand-in for a person who drags the robot's desired position.

In the given episodes it asks the task's ``scripted_human`` (:class:`khgrl.common.tasks.api.Task`) for P_h at each
step: from the step's KMP mean and, if the function asks for them, the step, its phase, the robot's position and
the environment's observation (:func:`khgrl.common.tasks.api.call_scripted_human`); optional seeded noise
imitates an unsteady hand; None releases. The passage world's (:class:`khgrl.common.tasks.passage.task.PassageGuide`)
knows a safe path through the gaps (and around the obstacle) -- the scenario's ``human_waypoints`` -- and, over
the part of the task where help is needed (the scenario's ``human_window``, in workspace x), sets P_h on that path
at the point the KMP mean has reached in x.

Its output is a correction P_h or ``None`` (released) per step: exactly what a person's drag produces.
The decision (:class:`ScriptedHuman`) and its single-process use (:class:`HumanCorrectionWrapper`, applied with
``set_correction``) are in :mod:`khgrl.common.tasks.scripted_human`, shared with the single-process reference; in the
distributed system ``khgrl human scripted`` (:func:`run`, :class:`ScriptedAnswers`) publishes it as
step-addressed correction messages that the actor applies the same way. That client drives the task the actors
run: its own (``--task``, ``--config``) while their frames name it, else the one they announce
(``task/actor/<id>``): started by hand without ``--task`` it still drives the run's task, and it refuses with one
line a task it cannot load here.
"""

from __future__ import annotations

import argparse
import sys
from typing import Callable

import numpy as np
from khgrl.common.config.process import ProcessConfig
from khgrl.common.config.settings import PAPER_EPISODES
from khgrl.common.delivery.task_link import fetch_tasks
from khgrl.common.process import StopFlag, install_stop_handlers
from khgrl.common.tasks.api import Task, TaskError, load_task
from khgrl.common.tasks.scripted_human import HumanCorrectionWrapper, ScriptedHuman, ScriptedHumanConfig, WholeEpisode
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.protocol import Frame
from khgrl.human_bridge.client import CorrectionPublisher, connected

__all__ = ["PAPER_EPISODES", "ScriptedHuman", "ScriptedHumanConfig", "HumanCorrectionWrapper", "ScriptedAnswers",
           "add_arguments", "run", "announced_task"]


# ------------------------------------------------------------------------------------ the scripted client
class ScriptedAnswers:
    """The scripted client's answer to each frame (lock-step, docs/distributed_runs.md).

    The frame describes step t. In a help episode it answers with a step-addressed correction for step t + 1
    (P_h from the KMP mean there, the robot and the observation the frame shows): the actor waits for it, so
    latency does not shift P_h against the mean. Other episodes: nothing (a hold left over is released). While the
    episode before a help episode runs, it announces lock-step for that episode with its word for step 0 (decided
    before that episode starts: the robot taken at the mean of step 0, no observation).

    :param human: the scripted human that decides P_h.
    :param pub: the correction stream to publish on.
    :param horizon: N, steps per episode (the phases s_t = t / (N - 1)); None: the phase is not known.
    """

    def __init__(self, human: ScriptedHuman, pub: CorrectionPublisher, horizon: int | None = None) -> None:
        self.human = human
        self.pub = pub
        self.phases = np.linspace(0.0, 1.0, horizon) if horizon and horizon > 1 else None
        # step -> KMP mean, from the latest frame of that step: the latest episode's (a varying-scene task's mean
        # changes every episode; the next episode's step-0 word is decided from the current episode's mean, the
        # best known before that episode's reset adapts it)
        self.means: dict[int, np.ndarray] = {}
        self.announced: set[tuple[str, int]] = set()  # (actor, episode) whose lock-step was announced

    def _phase(self, step: int) -> float | None:
        return float(self.phases[min(step, len(self.phases) - 1)]) if self.phases is not None else None

    def frame(self, f: Frame) -> None:
        """Answer one frame.

        :param f: the actor's frame of step ``f.t``.
        """
        ep, t, actor = f.episode, f.t, f.actor
        self.means[t] = f.mean
        if self.human.active_in(ep) and f.next_mean is not None:
            p_h = self.human.correction(ep, f.next_mean, step=t + 1, phase=self._phase(t + 1), position=f.robot,
                                        obs=f.obs)
            self.pub.send(actor, p_h, ep, t, step=t + 1)
        elif self.pub.active.get(actor, False):
            self.pub.send(actor, None, ep, t)
        if self.human.active_in(ep + 1) and (actor, ep + 1) not in self.announced:
            self.announced.add((actor, ep + 1))
            p0 = self.human.correction(ep + 1, self.means[0], step=0, phase=self._phase(0)) if 0 in self.means else None
            self.pub.send(actor, p0, ep + 1, t, step=0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The scripted client's own flags (its settings -- seed, episodes, noise -- are run settings; the task is the
    one the actors announce)."""
    parser.add_argument("--actor", default="*", help="actor id to drive (default: %(default)s, every actor)")
    parser.add_argument("--id", default="scripted", help="client id (default: %(default)s)")


def announced_task(announced: TaskDescriptor, cfg, say: Callable[[str], None] = print) -> Task:
    """The task an actor announced, loaded here for its ``scripted_human`` (a function: it does not travel on the
    wire, the task's spec does). The client's own ``--task``/``--scenario`` only matters where it is the same.

    :param announced: the actor's task descriptor.
    :param cfg: the client's run settings (``demos``, and ``task_spec`` to compare).
    :param say: where a note goes when the actor's task differs from this client's settings.
    :raises TaskError: one line: the task cannot be loaded here, is not the one announced, or has no scripted human.
    """
    spec = announced.spec
    if spec != cfg.task_spec:
        say(f"khgrl human scripted: the actor runs task {spec!r}; following it (this client's settings said "
            f"{cfg.task_spec!r})")
    try:
        task = load_task(spec, cfg.demos or None)
    except TaskError as exc:
        raise TaskError(f"the actor runs task {spec!r}, which this client cannot load: {exc}") from None
    if task.name != announced.name:
        raise TaskError(f"the actor runs task {announced.name!r} ({spec!r}); here that spec gives task "
                        f"{task.name!r}: run this client with the actor's code")
    if task.scripted_human is None:
        raise TaskError(f"the actor's task {task.name!r} has no scripted_human: use --human gui or none")
    return task


def _human(task: Task, cfg) -> ScriptedHuman:
    """The scripted human of ``task`` with the run's episodes, noise and seed; under ``--method hil-serl`` its
    ``takeover`` where it has one (the same human steering the robot from where it is), and with ``--takeover
    episode`` holding every step of its episodes (:class:`~khgrl.common.tasks.scripted_human.WholeEpisode`), with
    ``--takeover finish`` every step from its first takeover to the episode's end (``ScriptedHumanConfig.finish``)."""
    guide = task.scripted_human
    hil = cfg.method == "hil-serl"
    if hil:
        guide = getattr(guide, "takeover", guide)
        if cfg.takeover == "episode":
            guide = WholeEpisode(guide)
    return ScriptedHuman(guide, ScriptedHumanConfig(episodes=tuple(cfg.human_episodes), noise=cfg.human_noise,
                                                    seed=cfg.seed, finish=hil and cfg.takeover == "finish"))


def _horizon(task: Task, human: ScriptedHuman) -> int | None:
    """N (steps per episode, the demonstrations' length) where the scripted human asks for the phase."""
    from khgrl.common.tasks.api import task_demos

    return int(task_demos(task).shape[1]) if "phase" in human.inputs else None


class _Follower:
    """The answers for the task the actors run: this client's own task (``--task``, ``--config``) while the frames
    name it, else -- at the first frame of another task -- the task its actor announces (:func:`announced_task`).
    A frame names its task, so a client whose task is the run's answers from the first frame on, exactly as
    before; one started by hand without ``--task`` switches at the first frame.

    :param task: this client's own task.
    :param cfg: the run settings.
    :param link: the client's :class:`~khgrl.human_bridge.client.HumanClient`.
    """

    def __init__(self, task: Task, cfg, link) -> None:
        self.cfg, self.link, self.task = cfg, link, task
        human = _human(task, cfg)
        self.answers = ScriptedAnswers(human, link.pub, _horizon(task, human))

    def frame(self, f: Frame) -> None:
        if f.task != self.task.name:
            self._follow(f.actor)
        self.answers.frame(f)

    def _follow(self, actor: str) -> None:
        announced = fetch_tasks(self.link.session, self.link.keys, "actor", timeout=5.0,
                                rejects=self.link.rejects).get(actor)
        if announced is None:
            raise TaskError(f"actor {actor} runs a task other than {self.task.name!r} and does not say which")
        task = announced_task(announced, self.cfg)
        human = _human(task, self.cfg)
        self.task, self.answers = task, ScriptedAnswers(human, self.link.pub, announced.horizon)
        print(f"khgrl human scripted: now driving task {task.name!r}", flush=True)


def run(args: argparse.Namespace, proc: ProcessConfig) -> int:
    """``khgrl human scripted``: corrections from the task's scripted human in the run's ``human_episodes``, for the
    task the actors run (its own, or the one they announce: :class:`_Follower`).

    :param args: the parsed command line (:func:`add_arguments`).
    :param proc: the resolved run settings (run id, endpoint, task, seed, human_episodes, human_noise).
    """
    cfg = proc.cfg
    try:
        task = load_task(cfg.task_spec, cfg.demos or None)
        if task.scripted_human is None:
            raise TaskError(f"task {task.name!r} has no scripted_human: use --human gui or none")
    except TaskError as exc:
        print(f"khgrl human scripted: error: {exc}", file=sys.stderr, flush=True)
        return 2
    flag = StopFlag()
    install_stop_handlers(flag)
    print(f"khgrl human scripted ({args.id}) driving actor {args.actor} of run {proc.run} in episodes "
          f"{list(cfg.human_episodes)} (task {task.name!r}, or the one the actors announce)", flush=True)
    try:
        with connected(proc, args.id, flag, args.actor) as link:
            follower = _Follower(task, cfg, link)
            while not flag:
                got = link.next(timeout=0.2)
                if got is not None:
                    follower.frame(got[1])
                link.publish_status()
    except TaskError as exc:
        print(f"khgrl human scripted: error: {exc}", file=sys.stderr, flush=True)
        return 2
    except ValueError as exc:  # the task's scripted human gave something that is not a position
        print(f"khgrl human scripted: error: {exc}", file=sys.stderr, flush=True)
        return 1
    except ConnectionError as exc:
        if flag:
            return 0
        print(f"khgrl human scripted: {exc}", file=sys.stderr, flush=True)
        return 1
    print(f"khgrl human scripted: {link.frames} frames seen, {link.pub.sent} correction messages sent, "
          f"{link.rejects.total} rejected", flush=True)
    return 0
