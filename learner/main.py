"""``khgrl learner``: the learner process. sb3-contrib TQC (the paper's settings) trained ONLY from the
transition stream that actors publish over Zenoh; publishes the actor network by version; checkpoints and
resumes. See docs/protocol.md for the messages and the flow control.

    khgrl learner --config RUN_DIR/config.json [--resume]
    khgrl learner --run RUN --connect tcp/HOST:PORT --run-dir DIR [--learning-starts N ...]

The parts, in the order a transition meets them: the learner's link
(:class:`~khgrl.common.delivery.learner_link.LearnerLink`: its subscribers, the weights queryable, its liveliness
token) files the payload in an inbox; the ingest thread (:class:`~khgrl.common.delivery.learner_side.LearnerIngest`)
decodes and checks it, orders it into its actor's stream (:mod:`khgrl.common.delivery.ingest`) and hands it to
:mod:`khgrl.learner.trainer`, which stores it in the replay buffer (:mod:`khgrl.learner.replay`);
:mod:`khgrl.learner.loop` trains when an iteration is due; acks and weights go out through the link's publisher;
:mod:`khgrl.learner.journal` appends every stored batch to fsync'd segments in ``CHECKPOINT_DIR/journal`` (what
makes it durable for its actor); :mod:`khgrl.learner.checkpoint` saves the model on its own schedule
(``CHECKPOINT_DIR/model``) and, rarely, everything (``CHECKPOINT_DIR/checkpoint``; ``CHECKPOINT_DIR`` is
``RUN_DIR/learner`` unless ``--checkpoint-dir`` says); :mod:`khgrl.learner.resume` loads them and replays the
journal. A journal write or checkpoint that fails on a full or unwritable disk is logged, shown in the status and
retried while training goes on; if the final checkpoint fails the learner says so and exits with 1.
A router not reached within ``--connect-timeout`` is one error line naming it (exit 1).

One learner per run: a learner whose id is alive on the router (its liveliness token ``alive/learner/<id>/*``,
waited for up to the lease plus :data:`START_CHECK_S` to go, as a killed learner's does) refuses to start (one
error line, exit 2). With ``RUN_DIR/run.key`` (:mod:`~khgrl.common.delivery.run_key`) its acks and weights carry a
``mac``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from khgrl.common.config.process import ProcessConfig, add_process_flags, resolve_process
from khgrl.common.delivery.task_link import TASK_FILE, fetch_task, load_task_file, save_task
from khgrl.common.delivery.transport import open_client
from khgrl.common.process import StopFlag, die_with_parent, install_stop_handlers, setup_process_logging
from khgrl.common.wire.protocol import Keys
from khgrl.learner.algorithm import check_algorithm
from khgrl.learner.checkpoint import CheckpointError, can_resume
from khgrl.learner.journal_loss import ACCEPT_FLAG

if TYPE_CHECKING:
    from khgrl.learner.loop import LearnerLoop

__all__ = ["main", "build_parser", "START_CHECK_S"]

log = logging.getLogger("khgrl.learner")

START_CHECK_S = 2.0  # beyond the lease: how long a live learner of this id has to go before this one refuses


def build_parser() -> argparse.ArgumentParser:
    """``khgrl learner``'s flags: ``--config``, the learner's run settings, ``--id`` and ``--resume``."""
    p = argparse.ArgumentParser(
        prog="khgrl learner", description="TQC learner: trains from the actors' transition stream, publishes weights.")
    add_process_flags(p, "learner")  # the settings whose roles name the learner
    p.add_argument("--id", default="learner", help="learner id (default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="continue from the checkpoint and journal in RUN_DIR/learner (or --checkpoint-dir; an error "
                        "if there is neither; default: start afresh, removing an earlier learner's checkpoints)")
    p.add_argument(ACCEPT_FLAG, action="store_true",
                   help="with --resume: go on even if the journal lost batches it had confirmed (damage); actors "
                        "re-send those they still hold, the rest is counted lost and the learner exits with 3 "
                        "(default: off: such a journal is refused with one line naming the file, byte and batches)")
    return p


def _fail(message: object) -> int:
    """One line on stderr; the exit code of a usage error (2)."""
    print(f"khgrl learner: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    """Run the learner until SIGINT/SIGTERM or a ``stop`` command; 0 on a clean stop, 1 if the final checkpoint
    failed (or the router was unreachable), 2 on a usage error (or a damaged journal refused), 3 if a resumed
    learner lost confirmed batches (``--accept-journal-loss``, or batches no actor held any more).

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    """
    die_with_parent()
    args = build_parser().parse_args(argv)
    try:
        pc = resolve_process(args)
        keys = Keys(pc.run)
        check_algorithm(pc.cfg.algo)
    except (ValueError, FileNotFoundError) as exc:
        return _fail(exc)
    learner_dir = Path(pc.cfg.run_dir) / "learner"
    ckpt_dir = Path(pc.cfg.checkpoint_dir) if pc.cfg.checkpoint_dir else learner_dir
    if args.resume and not can_resume(ckpt_dir):
        return _fail(f"--resume: no checkpoint under {ckpt_dir}")
    if args.accept_journal_loss and not args.resume:
        return _fail(f"{ACCEPT_FLAG} goes with --resume")
    try:
        return run(pc, keys, args.id, learner_dir, resume=args.resume, accept_loss=args.accept_journal_loss)
    except CheckpointError as exc:
        return _fail(exc)


def run(pc: ProcessConfig, keys: Keys, learner_id: str, learner_dir: Path, *, resume: bool,
        accept_loss: bool = False) -> int:
    """The learner process after its flags are resolved.

    :param pc: the resolved configuration, run id and router endpoint
    :param keys: the run's key expressions
    :param learner_id: this learner's id
    :param learner_dir: ``RUN_DIR/learner``
    :param resume: continue from the checkpoint
    :param accept_loss: resume past journal damage (``--accept-journal-loss``)
    """
    import torch  # (imported here: --help and flag errors answer at once)
    from khgrl.common.delivery import run_key
    from khgrl.common.delivery.control_auth import ControlGate
    from khgrl.common.delivery.data_keys import DataKeys
    from khgrl.common.delivery.learner_link import LearnerLink
    from khgrl.common.delivery.role_keys import RoleKeyError
    from khgrl.learner.journal import Journal, journal_dir
    from khgrl.learner.loop import LearnerLoop
    from khgrl.learner.resume import open_learner
    from khgrl.learner.trainer import torch_device

    cfg = pc.cfg
    setup_process_logging(learner_dir / "learner.log")
    try:
        # acks and weights carry a mac and our signature; batches must (their actor's) when the run has keys
        key = DataKeys.of_run(cfg.run_dir, "learner", learner_id)
        gate = ControlGate.of_run(cfg.run_dir)  # control must carry the operator's signature when the run has keys
    except (run_key.RunKeyError, RoleKeyError) as exc:
        return _fail(exc)
    torch.set_num_threads(max(1, cfg.learner_threads))
    try:
        device = torch_device(cfg.tqc.device)
    except ValueError as exc:
        print(f"khgrl learner: error: {exc}", file=sys.stderr)
        return 2
    if cfg.learner_nice:
        os.nice(cfg.learner_nice)  # training yields the CPU to the actors' control loops on a shared machine
    flag = StopFlag()
    install_stop_handlers(flag)
    formats = ("csv", "tensorboard") if cfg.tensorboard else ("csv",)
    log.info("khgrl learner %s: run %s, connecting to %s", learner_id, pc.run, pc.endpoint)
    try:
        session = open_client(pc.endpoint, cfg.stream.lease_ms, stop=lambda: bool(flag), timeout=cfg.connect_timeout,
                              zenoh_config=pc.zenoh_config)
    except ConnectionError as exc:  # stopped while waiting for the router, or an endpoint Zenoh refuses
        log.info("%s", exc)
        if flag:
            return 0
        print(f"khgrl learner: error: {exc}", file=sys.stderr)
        return 1
    with session:
        if why := _other_learner(session, keys, learner_id, cfg.stream.lease_ms / 1000 + START_CHECK_S, flag):
            return _fail(why)
        task = run_task(session, keys, learner_dir, flag)
        if task is None:
            return 0
        trainer, streams = open_learner(cfg.tqc, cfg.seed, learner_dir, resume=resume, logger_formats=formats,
                                        task=task, checkpoint_dir=cfg.checkpoint_dir or None, algo=cfg.algo,
                                        accept_journal_loss=accept_loss)
        log.info("task %s (O = %d, %d observations, digest %s); epoch %s, learning_starts %d, training on %s",
                 task.name, task.out_dim, task.obs_dim, task.digest, trainer.epoch, trainer.learning_starts, device)
        journal = Journal(journal_dir(cfg.checkpoint_dir or learner_dir)) if cfg.stream.journal else None
        link = LearnerLink(session, keys, learner_id, task, key=key)
        loop = LearnerLoop(trainer, streams, link.publisher, learner_id=learner_id, learner_dir=learner_dir,
                           checkpoint_every=cfg.stream.checkpoint_every, flag=flag,
                           checkpoint_dir=cfg.checkpoint_dir or None, mode=cfg.stream.mode, journal=journal,
                           model_checkpoint_every=cfg.stream.model_checkpoint_every,
                           lead_cap=lead_cap(cfg.stream), key=key)
        loop.set_task(task, cfg.hilserl.teacher_demos)  # (the teacher's demonstrations are a0's first rows)
        loop.ingest.control = gate
        if streams.journal_loss is not None:  # (accepted): a full checkpoint replaces the damaged journal
            loop.durable.settle_loss()
        loop.start()
        link.announce(trainer.epoch)
        print(f"khgrl learner {learner_id} ready (epoch {trainer.epoch}, version {trainer.version}, "
              f"{trainer.total} transitions)", flush=True)
        try:
            loop.run(link.inbox)
            log.info("stopping (%s): final checkpoint", flag.reason or "stop")
            saved = loop.checkpoint() is not None
        finally:
            link.close()
    log.info("learner %s done: %s; inbox dropped %s", learner_id, loop.summary(), link.inbox.dropped)
    if not saved:
        return _final_checkpoint_failed(loop)
    return _lost(loop) if resume and loop.durable.lost_batches() else 0


def _lost(loop: LearnerLoop) -> int:
    """Say (log and stderr) that confirmed batches were lost -- journal damage accepted, batches no actor held any
    more -- and how many; exit code 3."""
    message = (f"{loop.durable.lost_batches()} batches confirmed durable before this learner resumed are lost "
               f"(journal damage: {loop.durable.summary()['journal_loss']}; skipped: {loop.streams.skipped})")
    log.error("%s", message)
    print(f"khgrl learner: error: {message}", file=sys.stderr, flush=True)
    return 3


def lead_cap(stream) -> int:
    """Simulation mode: how many transitions of an actor the learner stores ahead of what its trained weights cover.
    An actor waits once it has ``max_lead`` out beyond the ack's ``trained``, so with the batch it is cutting it never
    has more than ``max_lead + batch`` out; the learner counts a batch that an iteration covered in part as not
    covered: one batch more.

    :param stream: the run's :class:`~khgrl.common.config.settings.StreamSettings`
    """
    return int(stream.max_lead) + 2 * int(stream.batch)


def _final_checkpoint_failed(loop: LearnerLoop) -> int:
    """Say (log and stderr, no traceback) that the last checkpoint failed and what that means; exit code 1.

    :param loop: the learner loop whose final :meth:`~khgrl.learner.loop.LearnerLoop.checkpoint` failed
    """
    unsaved = loop.durable.not_durable()
    message = f"the final checkpoint in {loop.ckpt_dir} failed ({loop.durable.saves.error}): "
    if unsaved:
        message += (f"the {unsaved} transitions received that neither the last checkpoint nor the journal holds are "
                    f"lost here. Running actors keep every batch that acks never said durable and re-send it to a "
                    f"learner restarted with --resume once the disk is fixed")
    else:
        message += ("the last checkpoint and the journal hold every transition received, but not the training since "
                    "the last model checkpoint (a learner restarted with --resume trains from there)")
    log.error("%s", message)
    print(f"khgrl learner: error: {message}", file=sys.stderr, flush=True)
    return 1


def _other_learner(session, keys: Keys, learner_id: str, wait_s: float, flag: StopFlag) -> str | None:
    """Why this learner must not start: a learner with its id is alive on the router (asked before anything is
    declared), and its token did not go within ``wait_s`` s (None: there is none).

    :param session: the open Zenoh session
    :param keys: the run's key expressions
    :param learner_id: this learner's id
    :param wait_s: how long a live token has to go (a killed learner's goes within the lease)
    :param flag: the stop flag
    """
    from khgrl.common.delivery.learner_link import learner_alive

    deadline = time.monotonic() + wait_s
    alive = learner_alive(session, keys, learner_id)
    while alive and time.monotonic() < deadline and not flag:
        time.sleep(0.2)
        alive = learner_alive(session, keys, learner_id)
    if not alive:
        return None
    return (f"learner {learner_id} is already alive on the router ({', '.join(alive)}): one learner per run; a second "
            f"one with this id is refused (stop the other first)")


def run_task(session, keys: Keys, learner_dir: Path, flag: StopFlag):
    """The run's task descriptor: the one in ``learner/task.msgpack`` (written by ``khgrl up``, or saved by this
    learner in an earlier part of the run), or else the first an actor announces (waited for until a stop). The
    learner never imports a task's code.

    :param session: the open Zenoh session
    :param keys: the run's key expressions
    :param learner_dir: ``RUN_DIR/learner``
    :param flag: the stop flag (None is returned when it is set first)
    """
    path = learner_dir / TASK_FILE
    if path.is_file():
        return load_task_file(path)
    log.info("waiting for an actor to announce the run's task (%s)", keys.task("actor"))
    while not flag:
        task = fetch_task(session, keys, "actor", timeout=1.0, stop=lambda: bool(flag))
        if task is not None:
            save_task(path, task, "learner")
            return task
    return None


if __name__ == "__main__":
    sys.exit(main())
