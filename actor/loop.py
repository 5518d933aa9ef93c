"""The actor's control loop: episodes of the run's task, one step at a time.

Per control step:

1. between steps, the delivery layer (:class:`~khgrl.common.delivery.actor_side.ActorDelivery`) services the inbox
   -- acks, corrections, learner liveliness, control: :class:`~khgrl.actor.inbound.Inbound` -- swaps in new admitted
   policy weights, and holds the step back while the actor is too far ahead of the learner (``max_lead``) or paused;
2. pace to ``rate`` (:class:`~khgrl.actor.pacing.Pacer`), choose the action (uniform random, seeded, for the first
   ``learning_starts`` transitions of the run, as SB3 does; then ``policy.predict(obs, deterministic=False)``),
   apply the arbitrated correction (``env.set_correction``), step;
3. record the transition (the stored action is ``info["action"]``: the human's a_h when intervened), publish a
   frame (``last`` on the episode's final one), and every ``batch`` transitions of the actor's running index
   (and at episode end) cut a batch (:class:`~khgrl.common.delivery.stream.TransitionStream`).
The watchdog (:mod:`khgrl.actor.safety`) holds the robot, and says why, while the loop waits (the e-stop, a pause,
the learner) or a holding human is silent. First, demonstrations go out as prior transitions (:mod:`~.demos`,
:mod:`~.teach`). At the end the actor waits until the learner holds every batch in a checkpoint.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from khgrl.actor.demos import replay_demos
from khgrl.actor.inbound import Inbound
from khgrl.actor.pacing import Pacer
from khgrl.actor.parts import ActorParts
from khgrl.actor.physical import SOURCE
from khgrl.actor.reset import reset_phase
from khgrl.actor.safety import Watchdog
from khgrl.actor.supervision import Supervision
from khgrl.actor.teach import prepare
from khgrl.actor.telemetry import frame, status_info
from khgrl.common.config.settings import RunConfig
from khgrl.common.delivery.actor_side import ActorDelivery
from khgrl.common.metrics import EpisodeAccumulator
from khgrl.common.process import StopFlag
from khgrl.common.wire.messages import Dims, EpisodeReport, Status

__all__ = ["ActorParts", "ActorLoop"]  # (ActorParts: khgrl.actor.parts)
log = logging.getLogger("khgrl.actor")


@dataclass
class _Episode:
    """What one episode accumulates besides its statistics."""

    started: float
    segment: list = field(default_factory=list)  # the current intervention's (xi_h, phase) per step
    ret: float = 0.0


class ActorLoop:
    """Runs the episodes.

    :param cfg: the run's settings.
    :param actor: this actor's id.
    :param parts: the wired parts.
    :param flag: set by SIGINT/SIGTERM or a ``stop`` command.
    """

    def __init__(self, cfg: RunConfig, actor: str, parts: ActorParts, flag: StopFlag) -> None:
        self.cfg = cfg
        self.id = actor
        self.p = parts
        self.flag = flag
        self.realtime, self.demo_transitions, self.teacher = False, 0, None  # (teacher: actor/teach.py's record)
        self.episode = parts.episodes.last_episode
        self.first_episode = self.episode + 1
        self.earlier_transitions = parts.episodes.earlier_transitions
        self.pacer = Pacer(cfg.rate)
        tf = cfg.tqc.train_freq
        self.first_due = (cfg.tqc.learning_starts // tf + 1) * tf  # the first training iteration of the run
        self.dims = Dims(out=parts.env.mapping.model.out_dim)  # corrections carry O coordinates
        s = cfg.safety  # the e-stop state on disk, the supervisor's heartbeat (robot mode), before the first command
        self.inbound = Inbound(parts, flag, self.dims, parts.weights.receiver.gate,  # acks, corrections, liveliness
                               pause_s=cfg.stream.human_pause_s,
                               supervision=Supervision(s.supervised(cfg.stream.mode), s.supervision_timeout))
        self.inbound.restore_run_state(cfg.run_dir)
        self.delivery = ActorDelivery(actor, parts.link, parts.inbox, parts.stream, parts.weights, cfg.stream, flag,
                                      self.inbound, lambda item: self.inbound.handle(*item, episode=self.episode),
                                      self._publish_status)
        self.service, self.waits = self.delivery.service, self.delivery.waits
        self.watchdog = Watchdog(parts.env, self.inbound, parts.arbiter, s.human_silence_s, s.deadline_margin,
                                 self.pacer.period, self.service, self.rate_limit, self._publish_status,
                                 lambda: bool(flag))
        self.delivery.on_hold = self.watchdog.holding

    def join(self) -> None:
        """Before the first step: who is alive (waiting ``learner_wait`` s for one starting up), the current weights."""
        self.delivery.join()
        log.info("actor %s: learner %s, initial weights version %s", self.id,
                 "alive" if self.delivery.learner_alive else "not seen", self.p.weights.initial_version)

    # ------------------------------------------------------------------ episodes
    def run(self) -> int:
        """All remaining episodes, then the flush; returns the exit code (2, 3, 4: actor/main.py's docstring)."""
        acc = EpisodeAccumulator()
        acc.episode = self.episode  # a resumed run continues the numbering
        todo = self.cfg.episodes - self.episode
        self.pacer = Pacer(self.cfg.rate)
        self.p.scale.publish()
        self.demo_transitions = prepare(self) + replay_demos(self)  # (the teacher's or the task's, as prior data)
        if todo <= 0:
            log.info("all %d episodes of the run are done already: nothing to run", self.cfg.episodes)
        while len(self.p.episodes.new) < todo and not self.flag and not self.p.episodes.converged():
            if not self._episode(acc):
                break  # stopped mid-episode: no statistics for a partial episode
        if self.inbound.guard.fatal:  # another process publishes as this actor id: nothing more goes out on its stream
            return self.delivery.split_exit()
        self.p.stream.cut()  # a partial batch after a stop
        if self.inbound.wrong_task:  # only a learner of another task (and none of this one)
            print(f"khgrl actor {self.id}: error: {self.inbound.wrong_task}", file=sys.stderr, flush=True)
            return 2
        if self.flag:
            return self.delivery.finish_on_signal()
        return self.delivery.flush(len(self.p.episodes.new))  # (4 if another process as this actor stopped it)

    def _episode(self, acc: EpisodeAccumulator) -> bool:
        env = self.p.env
        if not reset_phase(self, self.episode + 1):  # the path back to the start, a person's ready
            return False
        obs, _ = env.reset_episode(self.episode + 1)
        acc.start()
        self.episode = acc.episode
        self.p.arbiter.new_episode(self.episode)
        self.p.steps.start(self.episode, env)
        ep = _Episode(started=time.perf_counter())
        done = False
        while not done and not self.flag:
            if not self.before_step():
                break
            obs, done = self._step(obs, acc, ep)
        if not done:
            return False
        self._end_episode(acc, ep, obs)
        return True

    def before_step(self) -> bool:
        """Inbox, flow control, pacing and the watchdog before a step; False if the actor is to stop."""
        self.service()
        self.rate_limit()
        if not self.flag and self.pacer.sleep():
            self.service()  # what arrived while pacing (a correction for the frame just published) applies now
            self.rate_limit()
        if self.watchdog.human_silence():  # held for a silent human: what arrived meanwhile (an e-stop) first
            self.rate_limit()
        self.watchdog.late(self.pacer.late)
        return not self.flag

    def _action(self, obs: np.ndarray) -> np.ndarray:
        run_index = self.earlier_transitions + self.p.stream.count - self.p.stream.start_index
        if run_index < self.cfg.tqc.learning_starts:
            return self.p.env.action_space.sample()
        action, _ = self.p.policy.predict(obs, deterministic=False)
        if run_index >= self.first_due:
            self.p.weights.note_lag(self.p.stream.count, self.cfg.stream.max_lead)
        return action

    def _step(self, obs: np.ndarray, acc: EpisodeAccumulator, ep: _Episode) -> tuple[np.ndarray, bool]:
        p, env = self.p, self.p.env
        self.pacer.step_started()
        action = self._action(obs)
        if not p.arbiter.ready(env.t):
            self.watchdog.await_word(env.t)  # (held meanwhile by the e-stop or a pause, until released)
            if self.flag:
                return obs, False  # stopped while waiting: no step
        p_h, physical = p.physical.correction(self.episode, p.arbiter.current(time.monotonic(), env.t))
        env.set_correction(p_h)  # (a hand on the arm, --physical, wins over a remote client's drag)
        before = env.position.copy()
        next_obs, reward, terminated, truncated, info = env.step(action)
        p.physical.observe(self.episode, int(info["t"]), before, info)
        acc.add(reward, info)
        ep.ret += float(reward)
        iv = bool(info["intervened"])
        if iv:
            ep.segment.append((info["xi_h"], info["phase"]))
        elif ep.segment:
            p.scale.refit(ep.segment, self.episode)
            ep.segment = []
        word = None if physical else p.arbiter.word  # (a human's signed correction vouches for the row)
        p.stream.add(obs, next_obs, info["action"], reward, terminated, truncated, iv, bool(info["clipped"]), word)
        p.steps.step(obs, info, env, reward, terminated, truncated, p_h, physical)
        t = int(info["t"])
        if iv and p_h is not None:
            p.record.write(self.episode, t, SOURCE if physical else p.arbiter.holder, p_h, info)
            p.arbiter.counts["projected_steps"] += int(bool(info.get("projected")))
        done = terminated or truncated
        p.link.publish(frame(env, self.id, self.episode, info, t, iv, ep.ret, done))
        if done or p.stream.count % self.cfg.stream.batch == 0:
            p.stream.cut()
        return next_obs, done

    def _end_episode(self, acc: EpisodeAccumulator, ep: _Episode, final_obs: np.ndarray) -> None:
        p = self.p
        p.env.set_correction(None)
        p.physical.end_episode()
        p.scale.refit(ep.segment, self.episode)
        st = acc.finish(time.perf_counter() - ep.started)
        p.record.flush()
        p.steps.finish(final_obs, st)  # (steps/episode-N.npz)
        p.tensorboard.episode(st)
        p.episodes.add(st, p.env.scene_row())
        p.link.publish(EpisodeReport(actor=self.id, stats=asdict(st)))
        log.info("episode %d: %d steps, return %.1f, success %s, interventions %d (%d steps), weights v%d",
                 st.episode, st.steps, st.ret, st.success, st.interventions, st.intervention_steps,
                 p.weights.version)

    # ------------------------------------------------------------------ delivery
    def _publish_status(self) -> None:
        p = self.p
        info = status_info(actor=self.id, episode=self.episode, t=p.env.t, stream=p.stream, weights=p.weights,
                           arbiter=p.arbiter, rejects=p.rejects, waits=self.waits,
                           learner_alive=self.delivery.learner_alive, paused=self.inbound.paused,
                           periods=self.pacer.periods)
        info = replace(info, alarm=self.inbound.guard.alarm or "",  # another process as this actor, two learners
                       held=self.watchdog.reason, safety=dict(self.watchdog.counts))
        p.link.publish(Status(role="actor", info=info))

    def rate_limit(self) -> None:
        """Flow control (:meth:`~khgrl.common.delivery.actor_side.ActorDelivery.rate_limit`); a correction held
        meanwhile is held as much longer."""
        waited = self.delivery.rate_limit()
        if waited is not None:
            self.p.arbiter.extend(waited)
            self.watchdog.released()
            self.pacer.resync()  # a hold is not lateness: the next step goes at once
