"""``khgrl actor``: the actor process. Steps the run's task (KGRL mapping, GPR exploration scale) with a
local copy of the TQC policy, applies human corrections that arrive over Zenoh, and streams its transitions
to the learner without losing or duplicating any.

    khgrl actor --config RUN_DIR/config.json --id a0 [--resume]
    khgrl actor --run RUN --connect tcp/HOST:PORT --run-dir DIR --id a0 [any run setting flag]

Wiring, top to bottom: settings -> logging and signals -> world and policy (seeded exactly as single-process
SB3 seeds them) -> Zenoh session (one error line and exit 1 if the router is not reached within ``--connect-timeout``)
-> the loop's parts (:mod:`khgrl.actor.loop`) -> run -> result files in
RUN_DIR/actor-ID/ (episodes.csv/json, corrections.csv, summary.json, config.json, scale.npz, tb/).
With ``--resume`` the actor continues the episode numbering of its earlier part and appends to its files.

One process per actor id: a second one with the same run directory is refused by the lock in RUN_DIR/actor-ID,
one elsewhere by the liveliness token of the live one (exit code 2, one line on stderr). A restarted actor
continues its transition stream (:mod:`khgrl.common.delivery.restart`): after a kill, without ``--resume`` too, it
re-sends
what the learner has not confirmed and appends to its episode and correction files.

Exit codes: 0 done (or stopped); 1 failed (e.g. no router); 2 a refused start, or no learner of this actor's task
(only one of another task); 3 the final flush timed out; 4 another process publishes as this actor id: acks claim
batches it never sent, acks of another stream of its id move on, or the learner superseded its stream
(:data:`~khgrl.common.delivery.actor_guard.SPLIT_EXIT`: one line with the id and stream ids, also in its status).
With ``RUN_DIR/run.key`` (:mod:`~khgrl.common.delivery.run_key`) the actor takes only acks and weights the learner
signed with it.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from khgrl.actor.arbiter import CorrectionArbiter
from khgrl.actor.exploration import ExplorationScale
from khgrl.actor.human_limits import Assignments, HoldAllowance
from khgrl.actor.loop import ActorLoop
from khgrl.actor.pacing import set_realtime
from khgrl.actor.parts import ActorParts
from khgrl.actor.physical import PhysicalHands
from khgrl.actor.record import CorrectionRecord
from khgrl.actor.results import EpisodeLog
from khgrl.actor.telemetry import TensorBoard
from khgrl.actor.telemetry import summary as actor_summary
from khgrl.actor.viewer import live_listeners
from khgrl.actor.weights import PolicyWeights, WeightsReceiver
from khgrl.common.config.process import ProcessConfig, add_process_flags, resolve_process
from khgrl.common.config.settings import HUMAN_METHODS
from khgrl.common.delivery import run_key
from khgrl.common.delivery.actor_link import ActorLink, actor_alive
from khgrl.common.delivery.control_auth import ControlGate
from khgrl.common.delivery.data_keys import DataKeys, Keyish
from khgrl.common.delivery.restart import AlreadyRunning, StreamRecord, StreamStart, lock_actor_dir, open_stream
from khgrl.common.delivery.role_keys import RoleKeyError
from khgrl.common.delivery.stream import TransitionStream
from khgrl.common.delivery.task_link import TaskAnnouncer
from khgrl.common.delivery.transport import Inbox, open_client
from khgrl.common.delivery.trust import WeightsGate
from khgrl.common.process import StopFlag, die_with_parent, install_stop_handlers, setup_process_logging
from khgrl.common.step_records import StepRecord
from khgrl.common.tasks.api import TaskError, load_task
from khgrl.common.tasks.scripted_human import ScriptedHuman, ScriptedHumanConfig
from khgrl.common.wire.checks import RejectCounter, ident
from khgrl.common.wire.protocol import Keys

__all__ = ["main", "build_parser", "run"]

log = logging.getLogger("khgrl.actor")

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl actor",
                                description="Actor: steps the run's task with the current policy, applies human "
                                            "corrections, streams transitions to the learner.")
    p.add_argument("--id", default="a0", help="actor id; actor a<i> is seeded with seed + i, another id with seed "
                   "+ a number made from it (default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="continue this actor's part of the run in RUN_DIR/actor-ID: its transition stream, episode "
                        "numbering, episodes.csv, corrections.csv and TensorBoard carry on (default: start afresh, "
                        "unless the earlier process was killed or left transitions the learner has not confirmed)")
    add_process_flags(p, "actor")  # the settings whose roles name the actor
    return p


def _build_parts(pc: ProcessConfig, actor: str, session, env, policy, out_dir: Path, start: StreamStart,
                 resume: bool, task=None, key: Keyish = None, physical: PhysicalHands | None = None,
                 control: ControlGate | None = None) -> ActorParts:
    """Declare everything on the session and wire the loop's parts (declaration order as the protocol expects:
    subscribers, publishers, the weights receiver, then the liveliness token)."""
    cfg, keys = pc.cfg, Keys(pc.run)
    rejects = RejectCounter(f"actor/{actor}")
    inbox = Inbox(maxsize=10_000, overflow="drop_oldest")
    link = ActorLink(session, keys, actor, inbox, rejects)
    receiver = WeightsReceiver(link.weights_subscriber(), policy.weights_template(), rejects, keys.weights,
                               gate=WeightsGate(key=key))
    receiver.start()
    announcer = TaskAnnouncer(session, keys, "actor", actor, task) if task is not None else None
    link.announce()
    rec = start.record
    stream = TransitionStream(actor, rec.stream, start.outbox, link.publish_transitions, rejects,
                              cfg.stream.resend_after_s, task=None if task is None else task.digest,
                              next_seq=rec.next_seq, next_index=rec.next_index, durable=rec.durable,
                              journal=lambda pos: StreamRecord(stream=rec.stream, **pos).save(out_dir),
                              window=cfg.stream.window, key=key)
    stream.bounds = task  # a transition outside the task's value bounds is not sent (the learner would refuse it)
    khgrl = cfg.method == "khgrl"  # (learns L; hil-serl's human takes over instead, KGRL's has no say)
    scale = ExplorationScale(env, actor, khgrl, link.publish)
    episodes = EpisodeLog(out_dir, resume, (cfg.until_success, cfg.success_window))
    if resume:
        scale.restore(out_dir)
    weights = PolicyWeights(policy, actor, receiver)
    views = live_listeners(pc.run, actor, env, lambda: weights.version)  # khgrl up --view ($KHGRL_VIEW); else ()
    return ActorParts(env=env, policy=policy, link=link, inbox=inbox, stream=stream,
                      arbiter=CorrectionArbiter(actor, cfg.stream.correction_timeout,
                                                enabled=cfg.method in HUMAN_METHODS,
                                                workspace=(env.world.low, env.world.high),
                                                allowance=HoldAllowance(cfg.stream.human_hold_s,
                                                                        cfg.stream.human_hold_refill),
                                                assignments=Assignments(actor, cfg.human_clients)),
                      weights=weights, scale=scale,
                      record=CorrectionRecord(out_dir / "corrections.csv", pc.run, actor, append=resume,
                                             dim=env.mapping.model.out_dim),
                      episodes=episodes, tensorboard=TensorBoard(out_dir / "tb" if cfg.tensorboard else None),
                      rejects=rejects, task=task, announcer=announcer, physical=physical or PhysicalHands.off(),
                      steps=StepRecord(out_dir, listeners=views), control=control or ControlGate.of_run(None))


def _physical(cfg, env, out_dir: Path) -> PhysicalHands:
    """``--physical``: detection (and the scripted physical human of the human episodes); raises TaskError."""
    if cfg.physical == "off":
        return PhysicalHands.off()
    human = None
    if cfg.physical == "scripted":
        if env.task.scripted_human is None:
            raise TaskError(f"task {env.task.name!r} has no scripted human to decide where the physical one pushes")
        human = ScriptedHuman(env.task.scripted_human, ScriptedHumanConfig(episodes=cfg.human_episodes, seed=cfg.seed))
    return PhysicalHands(env, cfg.physical, human, out_dir)


def _summary(loop: ActorLoop, rc: int, wall: float) -> dict:
    """``summary.json`` of this part of the run.

    :param loop: the actor's loop.
    :param rc: the exit code.
    :param wall: seconds the run took.
    """
    p = loop.p
    out = actor_summary(actor=loop.id, rc=rc, stopped_by=loop.flag.reason, wall=wall, episodes=p.episodes.new,
                        first_episode=loop.first_episode, stream=p.stream, weights=p.weights, arbiter=p.arbiter,
                        rejects=p.rejects, waits=loop.waits, max_lead=loop.cfg.stream.max_lead, rate=loop.cfg.rate,
                        periods=loop.pacer.periods, scale_updates=p.scale.updates, realtime=loop.realtime)
    return {**out, "demo_transitions": loop.demo_transitions, "teacher": loop.teacher, "converged": p.episodes.reached,
            "safety": loop.watchdog.summary(),
            "physical": p.physical.counts}


def _close(parts: ActorParts) -> None:
    parts.steps.close()  # (a live view's last data)
    parts.record.close()
    parts.physical.close()
    parts.weights.receiver.stop()
    if parts.announcer is not None:
        parts.announcer.undeclare()
    parts.link.close()
    parts.tensorboard.close()


def _error(actor: str, message: object) -> int:
    """Log and print one error line; the exit code of a refused start (2)."""
    log.error("%s", message)
    print(f"khgrl actor {actor}: error: {message}", file=sys.stderr, flush=True)
    return 2


def run(pc: ProcessConfig, actor: str, resume: bool) -> int:
    """Run one actor to the end; returns its exit code (0 done, 3 flush timed out, 1 failed).

    :param pc: the resolved settings, run id and router endpoint.
    :param actor: this actor's id.
    :param resume: continue the actor's earlier part of the run.
    """
    import torch
    from khgrl.common.tasks.kgrl_env import KGRLEnv
    from khgrl.learner.algorithm import algorithm_class

    cfg = pc.cfg
    seed = cfg.actor_seed(actor)
    out_dir = Path(cfg.run_dir) / f"actor-{actor}"
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        lock = lock_actor_dir(out_dir)  # held until this process ends
    except AlreadyRunning as exc:
        print(f"khgrl actor {actor}: error: actor {actor} is already running: {exc}", file=sys.stderr, flush=True)
        return 2
    setup_process_logging(out_dir / "actor.log")
    try:
        # acks and weights must carry the learner's mac and signature when the run has keys; batches carry ours
        key = DataKeys.of_run(cfg.run_dir, "actor", actor)
        gate = ControlGate.of_run(cfg.run_dir)  # control must carry the operator's (a client's) signature
    except (run_key.RunKeyError, RoleKeyError) as exc:
        return _error(actor, exc)
    if not gate.active:
        log.warning("no role keys in %s (khgrl keys RUN_DIR): control is not authenticated, anyone on the router may "
                    "release the e-stop or stop this actor", cfg.run_dir)
    torch.set_num_threads(1)
    flag = StopFlag()
    install_stop_handlers(flag)

    t0 = time.perf_counter()
    try:
        env = KGRLEnv(load_task(cfg.task_spec, cfg.demos or None), seed=seed, adapt=cfg.adapt,
                      control="delta" if cfg.method == "hil-serl" else "kmp",
                      rate_limit=cfg.safety.limits(cfg.stream.mode))
        task = env.descriptor(cfg.task_spec)
        physical = _physical(cfg, env, out_dir)
    except TaskError as exc:
        return _error(actor, exc)
    env.action_space.seed(seed)  # SB3 seeds the action space it samples warm-up actions from
    torch.manual_seed(seed)
    try:  # the learner algorithm's policy network (--algo), on the CPU, in evaluation mode
        policy = algorithm_class(cfg.algo).actor_policy(env.observation_space, env.action_space, cfg.tqc)
    except ValueError as exc:
        return _error(actor, exc)
    log.info("actor %s (seed %d): task %s (O = %d, %d observations, digest %s), %s, world ready in %.1f s", actor,
             seed, cfg.task_spec, task.out_dim, task.obs_dim, task.digest, cfg.method, time.perf_counter() - t0)

    rc = 1
    t_run = time.perf_counter()
    try:
        session = open_client(pc.endpoint, cfg.stream.lease_ms, stop=lambda: bool(flag), timeout=cfg.connect_timeout,
                              zenoh_config=pc.zenoh_config)
    except ConnectionError as exc:  # stopped while waiting, no router within --connect-timeout, or a bad endpoint
        if flag:
            return 0
        log.error("%s", exc)
        print(f"khgrl actor {actor}: error: {exc}", file=sys.stderr, flush=True)
        return 1
    with session:
        if other := actor_alive(session, Keys(pc.run), actor):
            return _error(actor, f"actor {actor} is already alive on the router ({other}): a second process with "
                                 f"this id is refused (give it another --id)")
        start = open_stream(out_dir, cfg.stream.outbox_memory, actor, resume)
        resume = resume or start.continued
        parts = _build_parts(pc, actor, session, env, policy, out_dir, start, resume, task, key, physical, gate)
        loop = ActorLoop(cfg, actor, parts, flag)
        loop.join()
        loop.realtime = set_realtime(cfg.actor_rt_priority) if cfg.actor_rt_priority > 0 else False
        try:
            rc = loop.run()
        finally:
            summary = _summary(loop, rc, time.perf_counter() - t_run)
            _close(parts)
            StreamRecord(stream=parts.stream.stream, **parts.stream.position(), running=False).save(out_dir)

    runtime = {**pc.runtime, "run": pc.run, "endpoint": pc.endpoint, "actor_id": actor, "seed": seed,
               "stream": parts.stream.stream, "resumed": resume, "first_episode": loop.first_episode,
               "continued_stream": start.continued, "after_kill": start.killed}
    parts.scale.save(out_dir)
    parts.episodes.write_final({**cfg.to_dict(), "runtime": runtime}, summary)
    log.info("actor %s done (exit %d): %d episodes, %d transitions, loop period p50 %.2f ms p99 %.2f ms",
             actor, rc, len(parts.episodes.new), summary["transitions"], summary["loop_period_ms"]["p50"] or 0,
             summary["loop_period_ms"]["p99"] or 0)
    lock.close()
    return rc


def main(argv: list[str] | None = None) -> int:
    die_with_parent()
    args = build_parser().parse_args(argv)
    try:
        pc = resolve_process(args)
        Keys(pc.run)
        ident("--id", args.id)
    except (ValueError, FileNotFoundError) as exc:
        print(f"khgrl actor: error: {exc}", file=sys.stderr)
        return 2
    return run(pc, args.id, args.resume)


if __name__ == "__main__":
    sys.exit(main())
