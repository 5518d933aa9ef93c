"""The actor's control loop: episodes of the run's task, one step at a time.

Per control step:

1. service the inbox (acks, corrections, learner liveliness, control: :mod:`khgrl.actor.inbound`) and swap in new policy
   weights if the background receiver has a validated, admitted state dict ready (no stall: the swap is a
   ``load_state_dict``; :mod:`khgrl.common.delivery.trust` says which weights are admitted);
2. rate limit: while the learner is alive, wait while ``sent - ack.trained >= max_lead`` or the loaded
   weights are older than ``ack.version``. The transition about to be collected would otherwise make the
   actor more than ``max_lead`` transitions ahead of what the learner has trained on. With ``max_lead`` =
   ``batch`` = the train frequency (the defaults) each step is taken with exactly the weights single-process
   SB3 would use: the weights trained at the last multiple of ``train_freq`` (after ``learning_starts``).
   If the learner is not alive, or in ``--mode robot``, the actor keeps acting with its last weights (a robot
   does not stop for the learner);
3. pace to ``rate`` (:class:`~khgrl.actor.pacing.Pacer`), choose the action (uniform random, seeded, for the first
   ``learning_starts`` transitions of the run, as SB3 does; then ``policy.predict(obs, deterministic=False)``),
   apply the arbitrated correction (``env.set_correction``), step;
4. record the transition (the stored action is ``info["action"]``: the human's a_h when intervened), publish a
   frame (``last`` on the episode's final one), and every ``batch`` transitions of the actor's running index
   (and at episode end) cut a batch (:class:`~khgrl.common.delivery.stream.TransitionStream`).

At the end the actor waits until the learner holds every batch in a checkpoint (``flush_timeout``).
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from khgrl.actor.arbiter import CorrectionArbiter
from khgrl.actor.exploration import ExplorationScale
from khgrl.actor.inbound import Inbound
from khgrl.actor.pacing import Pacer
from khgrl.actor.record import CorrectionRecord
from khgrl.actor.results import EpisodeLog
from khgrl.actor.telemetry import RateLimitStats, TensorBoard, frame, status_info, summary
from khgrl.actor.weights import PolicyWeights
from khgrl.common.config.settings import RunConfig
from khgrl.common.delivery.actor_link import ActorLink
from khgrl.common.delivery.stream import TransitionStream
from khgrl.common.delivery.transport import Inbox
from khgrl.common.metrics import EpisodeAccumulator
from khgrl.common.process import StopFlag
from khgrl.common.wire.checks import RejectCounter
from khgrl.common.wire.messages import Dims, EpisodeReport, Status

__all__ = ["ActorParts", "ActorLoop"]

log = logging.getLogger("khgrl.actor")

MAX_SERVICE = 16  # messages handled per control step at most (a step needs ~2: a correction, an ack)
POLL_S = 0.002  # while waiting for messages: how often the ring buffers are looked at
STATUS_EVERY_S = 1.0
FINISH_WAIT_S = 5.0  # stopped mid-run: how long the actor waits for the learner to checkpoint its last batches


@dataclass
class ActorParts:
    """The pieces the loop drives (built and wired by :mod:`khgrl.actor.main`)."""

    env: Any  # khgrl.common.tasks.kgrl_env.KGRLEnv (the task behind the KGRL mapping)
    policy: Any  # sb3_contrib TQCPolicy
    link: ActorLink
    inbox: Inbox
    stream: TransitionStream
    arbiter: CorrectionArbiter
    weights: PolicyWeights
    scale: ExplorationScale
    record: CorrectionRecord
    episodes: EpisodeLog
    tensorboard: TensorBoard
    rejects: RejectCounter
    task: Any = None  # khgrl.common.wire.descriptor.TaskDescriptor this actor announced
    announcer: Any = None  # khgrl.common.delivery.task_link.TaskAnnouncer


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
        self.realtime = False
        self.episode = parts.episodes.last_episode
        self.first_episode = self.episode + 1
        self.earlier_transitions = parts.episodes.earlier_transitions
        self.waits = RateLimitStats()
        self.pacer = Pacer(cfg.rate)
        tf = cfg.tqc.train_freq
        self.first_due = (cfg.tqc.learning_starts // tf + 1) * tf  # the first training iteration of the run
        self._t_status = time.monotonic()
        self.dims = Dims(out=parts.env.mapping.model.out_dim)  # corrections carry O coordinates
        self.inbound = Inbound(parts, flag, self.dims)  # acks, corrections, control, learner liveliness

    @property
    def learner_alive(self) -> bool:
        return bool(self.inbound.learners)

    @property
    def paused(self) -> bool:
        return self.inbound.paused

    @property
    def wrong_task(self) -> str | None:
        """Why this actor refused its learner or was refused (exit code 2)."""
        return self.inbound.wrong_task

    def join(self) -> None:
        """Before the first step: who is alive (waiting ``learner_wait`` s for one starting up), the current weights."""
        self.inbound.join(self.p.link.learners_alive(timeout=1.0))
        deadline = time.monotonic() + self.cfg.stream.learner_wait
        while not self.learner_alive and not self.flag and time.monotonic() < deadline:
            self.service(block=0.1)  # a learner that appears is reported (and its task checked) by Inbound
        self._query_weights(timeout=2.0)
        w = self.p.weights
        w.initial_version = w.version if w.version >= 0 else None
        log.info("actor %s: learner %s, initial weights version %s", self.id,
                 "alive" if self.learner_alive else "not seen", w.initial_version)

    # ------------------------------------------------------------------ episodes
    def run(self) -> int:
        """All remaining episodes, then the flush; returns the exit code (3: flush timed out)."""
        acc = EpisodeAccumulator()
        acc.episode = self.episode  # a resumed run continues the numbering
        todo = self.cfg.episodes - self.episode
        self.pacer = Pacer(self.cfg.rate)
        self.p.scale.publish()
        if todo <= 0:
            log.info("all %d episodes of the run are done already: nothing to run", self.cfg.episodes)
        while len(self.p.episodes.new) < todo and not self.flag:
            if not self._episode(acc):
                break  # stopped mid-episode: no statistics for a partial episode
        self.p.stream.cut()  # a partial batch after a stop
        if self.wrong_task:
            print(f"khgrl actor {self.id}: error: {self.wrong_task}", file=sys.stderr, flush=True)
            return 2
        if self.flag:
            return self._finish_on_signal()
        return self._flush()

    def _episode(self, acc: EpisodeAccumulator) -> bool:
        env = self.p.env
        obs, _ = env.reset()
        acc.start()
        self.episode = acc.episode
        self.p.arbiter.new_episode(self.episode)
        ep = _Episode(started=time.perf_counter())
        done = False
        while not done and not self.flag:
            if not self._before_step():
                break
            obs, done = self._step(obs, acc, ep)
        if not done:
            return False
        self._end_episode(acc, ep)
        return True

    def _before_step(self) -> bool:
        """Inbox, flow control and pacing before a step; False if the actor is to stop."""
        self.service()
        self.rate_limit()
        if self.flag:
            return False
        if self.pacer.sleep():
            # what arrived while pacing (a correction for the frame just published) applies to this step
            self.service()
            self.rate_limit()
            if self.flag:
                return False
        return True

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
            self._await_correction(env.t)
        p_h = p.arbiter.current(time.monotonic(), env.t)
        env.set_correction(p_h)
        next_obs, reward, terminated, truncated, info = env.step(action)
        acc.add(reward, info)
        ep.ret += float(reward)
        iv = bool(info["intervened"])
        if iv:
            ep.segment.append((info["xi_h"], info["phase"]))
        elif ep.segment:
            p.scale.refit(ep.segment, self.episode)
            ep.segment = []
        p.stream.add(obs, next_obs, info["action"], reward, terminated, truncated, iv, bool(info["clipped"]))
        t = int(info["t"])
        if iv and p_h is not None:
            p.record.write(self.episode, t, p.arbiter.holder, p_h, info)
            p.arbiter.counts["projected_steps"] += int(bool(info.get("projected")))
        done = terminated or truncated
        p.link.publish(frame(env, self.id, self.episode, info, t, iv, ep.ret, done))
        if done or p.stream.count % self.cfg.stream.batch == 0:
            p.stream.cut()
        return next_obs, done

    def _end_episode(self, acc: EpisodeAccumulator, ep: _Episode) -> None:
        p = self.p
        p.env.set_correction(None)
        p.scale.refit(ep.segment, self.episode)
        st = acc.finish(time.perf_counter() - ep.started)
        p.record.flush()
        p.tensorboard.episode(st)
        p.episodes.add(st)
        p.link.publish(EpisodeReport(actor=self.id, stats=asdict(st)))
        log.info("episode %d: %d steps, return %.1f, success %s, interventions %d (%d steps), weights v%d",
                 st.episode, st.steps, st.ret, st.success, st.interventions, st.intervention_steps,
                 p.weights.version)

    # ------------------------------------------------------------------ inbox
    def service(self, block: float = 0.0) -> None:
        """Handle what arrived -- at most :data:`MAX_SERVICE` messages, so a flood costs a step a bounded time (the
        rest waits in Zenoh's ring buffers, which keep the newest, or in the bounded inbox) -- waiting up to
        ``block`` s for the first when nothing is waiting; swap weights; re-send if stalled; publish the status about
        once a second.

        :param block: seconds to wait for something to arrive.
        """
        first = self._arrivals(block)
        for item in first:
            self.inbound.handle(*item, episode=self.episode)
        for _ in range(MAX_SERVICE - len(first)):
            item = self.p.inbox.get()
            if item is None:
                break
            self.inbound.handle(*item, episode=self.episode)
        self.p.weights.swap()
        self.p.stream.check_resend(self.learner_alive)
        now = time.monotonic()
        if now - self._t_status >= STATUS_EVERY_S:
            self._t_status = now
            self._publish_status()

    def _arrivals(self, block: float) -> list[tuple]:
        """What waits in the link's ring buffers (at most :data:`MAX_SERVICE`), else the inbox's next item, waiting
        up to ``block`` s for either (the rings are looked at every :data:`POLL_S`)."""
        end = time.monotonic() + block
        while True:
            polled = self.p.link.rings.poll(MAX_SERVICE)
            if polled:
                return polled
            left = end - time.monotonic()
            item = self.p.inbox.get(min(POLL_S, left) if left > 0 else 0.0)
            if item is not None or left <= 0:
                return [] if item is None else [item]

    def _publish_status(self) -> None:
        p = self.p
        info = status_info(actor=self.id, episode=self.episode, t=p.env.t, stream=p.stream, weights=p.weights,
                           arbiter=p.arbiter, rejects=p.rejects, waits=self.waits, learner_alive=self.learner_alive,
                           paused=self.paused, periods=self.pacer.periods)
        p.link.publish(Status(role="actor", info=info))

    def _query_weights(self, timeout: float) -> None:
        """Pull the current weights from the learner's queryable (late joiner / missed update)."""
        self.p.weights.last_query = time.monotonic()
        self.p.weights.load_replies(self.p.link.query_weights(timeout))

    # ------------------------------------------------------------------ waiting
    def _must_wait(self) -> bool:
        if self.paused:
            return True
        if not self.learner_alive or self.cfg.stream.mode == "robot":  # a robot does not wait for the learner
            return False
        s = self.p.stream
        trained = s.trained if s.ack_epoch is not None else s.start_index  # (a continued stream: trained before)
        return s.sent - trained >= self.cfg.stream.max_lead or self.p.weights.behind(s.ack_epoch, s.ack_version)

    def rate_limit(self) -> None:
        """Wait (servicing the inbox) while the actor is too far ahead of the learner or paused."""
        if not self._must_wait():
            return
        t0 = time.monotonic()
        self.waits.waits += 1
        w, s = self.p.weights, self.p.stream
        while not self.flag and self._must_wait():
            self.service(block=0.02)
            now = time.monotonic()
            if w.behind(s.ack_epoch, s.ack_version) and now - t0 > 1.0 and now - w.last_query > 1.0:
                self._query_weights(timeout=1.0)
        dt = time.monotonic() - t0
        self.waits.wait_s += dt
        self.p.arbiter.extend(dt)

    def _await_correction(self, step: int) -> None:
        """A lock-step correction client has not yet sent its word for ``step``: wait for it (servicing the
        inbox) at most the correction timeout, then carry on without it."""
        t0 = time.monotonic()
        arb = self.p.arbiter
        arb.counts["lockstep_waits"] += 1
        while not self.flag and not arb.ready(step):
            if time.monotonic() - t0 > arb.timeout:
                arb.give_up(step)
                break
            self.service(block=0.002)

    # ------------------------------------------------------------------ the end
    def _flush(self) -> int:
        """Wait until the learner holds every batch in a checkpoint (or ``flush_timeout``)."""
        s = self.p.stream
        last = s.highest_sent
        t0 = time.monotonic()
        log.info("all %d episodes done: flushing %d batches (last seq %d)", len(self.p.episodes.new), len(s.outbox),
                 last)
        while last >= 0 and s.durable < last and time.monotonic() - t0 < self.cfg.stream.flush_timeout \
                and not self.flag:
            self.service(block=0.05)
            if s.checkpoint_due(self.learner_alive):
                self.p.link.request_checkpoint()
        self._publish_status()
        if s.durable < last:
            n = s.unconfirmed()
            log.error("flush timed out: %d transitions in %d batches not confirmed durable by the learner", n,
                      len(s.outbox))
            print(f"khgrl actor {self.id}: flush timed out: {n} transitions not confirmed", file=sys.stderr, flush=True)
            return 3
        log.info("flushed: every batch up to seq %d is in a learner checkpoint", last)
        return 0

    def _finish_on_signal(self) -> int:
        """Stopped mid-episode (a signal or a stop command): publish what was collected since the last batch, then
        give the learner up to :data:`FINISH_WAIT_S` to hold every batch in a checkpoint (``khgrl up`` stops the
        actors before the learner, so its final checkpoint has them); what it does not hold stays in the outbox on
        disk, for this actor id restarted with ``--resume`` to re-send."""
        s = self.p.stream
        s.cut()
        last = s.highest_sent
        t0 = time.monotonic()
        while last >= 0 and s.durable < last and self.learner_alive and time.monotonic() - t0 < FINISH_WAIT_S:
            self.service(block=0.05)
            if s.checkpoint_due(self.learner_alive):
                self.p.link.request_checkpoint()
        log.info("stopped (%s): %d transitions not yet durable", self.flag.reason, s.unconfirmed())
        return 0

    def summary(self, rc: int, wall: float) -> dict:
        """``summary.json`` of this part of the run.

        :param rc: the exit code.
        :param wall: seconds the run took.
        """
        p = self.p
        return summary(actor=self.id, rc=rc, stopped_by=self.flag.reason, wall=wall, episodes=p.episodes.new,
                       first_episode=self.first_episode, stream=p.stream, weights=p.weights, arbiter=p.arbiter,
                       rejects=p.rejects, waits=self.waits, max_lead=self.cfg.stream.max_lead, rate=self.cfg.rate,
                       periods=self.pacer.periods, scale_updates=p.scale.updates, realtime=self.realtime)
