"""The plan of one start of ``khgrl up``: the resolved settings, the checked run directory and the run's runtime
facts (:class:`RunPlan`, :func:`plan_run`), then the configuration files written before any process starts
(:func:`prepare_run_dir`). Nothing here starts a process: :mod:`khgrl.deploy.run.launcher` does.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from khgrl.common.config.hilserl import recipe_runtime
from khgrl.common.config.settings import RunConfig, resolve, write_run_config
from khgrl.common.delivery import role_keys, run_key
from khgrl.common.delivery.task_link import TASK_FILE, save_task
from khgrl.common.delivery.transport import free_port
from khgrl.common.delivery.zenoh_config import config_file
from khgrl.common.wire.protocol import Keys
from khgrl.deploy.run import rundir
from khgrl.deploy.run.preflight import check_task
from khgrl.deploy.run.rundir import RunDirError
from khgrl.deploy.run.secure import SecureRun, prepare_secure_run, run_identities
from khgrl.learner.algorithm import check_algorithm

__all__ = ["RunPlan", "plan_run", "prepare_run_dir"]


@dataclass
class RunPlan:
    """What a start of ``khgrl up`` runs: the resolved settings and the run's runtime facts."""

    cfg: RunConfig
    run_dir: Path
    run_id: str
    endpoint: str
    resume: bool = False
    overwrite: bool = False
    progress: bool = True
    argv: list[str] = field(default_factory=list)
    previous: dict = field(default_factory=dict)  # runtime of the part before (resume)
    task: Any = None  # the run's TaskDescriptor (the learner gets it from RUN_DIR/learner/task.msgpack)
    secure: bool = False  # --secure: mTLS + access control (certificates in RUN_DIR/certs)
    zenoh_config: str | None = None  # --zenoh-config for every process (not with --secure)
    secure_run: SecureRun | None = None  # made by prepare_run_dir with --secure
    bounds: dict = field(default_factory=dict)  # the task's value bounds: stated or derived (with the rule)

    def zenoh_file(self, role: str, ident: str | None = None) -> str | None:
        """The Zenoh configuration of a process (its own identity's with --secure), or None."""
        return self.secure_run.config_for(role, ident) if self.secure_run is not None else self.zenoh_config

    def zenoh_args(self, role: str, ident: str | None = None) -> list[str]:
        """``--zenoh-config FILE`` for a process, or nothing."""
        file = self.zenoh_file(role, ident)
        return ["--zenoh-config", file] if file else []

    @property
    def config_json(self) -> Path:
        return self.run_dir / "config.json"


def _resolve_config(args: argparse.Namespace) -> RunConfig:
    """Defaults < --config < flags; on ``--resume`` without ``--config``: RUN_DIR/config.toml is the file."""
    cfg = resolve(args.config, args)
    if not args.resume or args.config:
        return cfg
    base = Path(cfg.run_dir) / "config.toml"
    if not base.is_file():
        raise RunDirError(f"--resume: nothing to resume in {cfg.run_dir}: it has no config.toml")
    return resolve(base, args, overrides={"run_dir": cfg.run_dir})


def _check_run_dir(run_dir: Path, args: argparse.Namespace, checkpoint_dir: str = "") -> None:
    found = rundir.results_in(run_dir)
    if args.resume:
        if not (run_dir / "config.toml").is_file():
            raise RunDirError(f"--resume: nothing to resume in {run_dir}: it has no config.toml")
        if not rundir.has_checkpoint(run_dir, checkpoint_dir):
            raise RunDirError(f"--resume: nothing to resume in {run_dir}: no learner checkpoint "
                              f"(learner/checkpoint/state.json); start it again with --overwrite")
    elif found and not args.overwrite:
        raise RunDirError(f"run directory {run_dir} already holds a run ({', '.join(found)}): give --resume to "
                          f"continue it, --overwrite to delete it and start again, or another --run-dir")
    elif found:
        rundir.refuse_live(run_dir)  # --overwrite deletes only a run that has ended


def plan_run(args: argparse.Namespace, argv: list[str]) -> RunPlan:
    """Resolve the configuration and check the run directory (nothing is written yet).

    :param args: parsed ``khgrl up`` arguments
    :param argv: the command line, recorded in config.json
    :raises RunDirError: the run directory cannot be used as asked
    :raises ValueError: a bad setting"""
    cfg = _resolve_config(args)
    if cfg.demos:
        cfg = dataclasses.replace(cfg, demos=rundir.resolve_demos(cfg.demos))
    run_dir = Path(cfg.run_dir)
    _check_run_dir(run_dir, args, cfg.checkpoint_dir)
    check_algorithm(cfg.algo)
    bounds: dict = {}  # the task's value bounds and how they came about (config.json: runtime.task_bounds)
    task = check_task(cfg, bounds)
    previous = rundir.previous_runtime(run_dir) if args.resume else {}
    run_id = cfg.run or str(previous.get("run") or "") or rundir.make_run_id(run_dir)
    Keys(run_id)  # a valid key chunk (ValueError otherwise)
    if args.secure and cfg.connect:
        raise ValueError("--secure starts its own router with certificates made for the run; to join a router "
                         "elsewhere give --connect with --zenoh-config (README: Running across machines)")
    scheme = "tls" if args.secure else "tcp"
    endpoint = cfg.connect or f"{scheme}/127.0.0.1:{cfg.port or free_port()}"
    return RunPlan(cfg=cfg, run_dir=run_dir, run_id=run_id, endpoint=endpoint, resume=args.resume,
                   overwrite=args.overwrite, progress=args.progress, argv=argv, previous=previous, task=task,
                   secure=args.secure, zenoh_config=config_file(args.zenoh_config), bounds=bounds)


def prepare_run_dir(plan: RunPlan) -> None:
    """Clear (``--overwrite``) or archive the part before (``--resume``), then write the configuration files.

    :param plan: the run's plan"""
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    part = 1
    if plan.overwrite:
        deleted = rundir.clear_run(plan.run_dir)
        if deleted:
            print(f"khgrl up: --overwrite: deleted the earlier run in {plan.run_dir} ({', '.join(deleted)})",
                  flush=True)
    if plan.resume:
        part = int(plan.previous.get("part", 1)) + 1
        rundir.archive_part(plan.run_dir, part - 1)
    if plan.cfg.demos and not plan.resume:  # the run keeps the demonstrations it was trained from
        kept = rundir.keep_demos(plan.run_dir, plan.cfg.task_spec, plan.cfg.demos)
        plan.cfg = dataclasses.replace(plan.cfg, demos=str(kept))
    run_key.create(plan.run_dir, fresh=not plan.resume)  # the learner signs acks and weights, actors check
    role_keys.make_run_keys(plan.run_dir, run_identities(plan.cfg), fresh=not plan.resume)  # the operator signs control
    if plan.secure:
        plan.secure_run = prepare_secure_run(plan.run_dir, plan.endpoint, run_identities(plan.cfg))
    runtime = {"run": plan.run_id, "endpoint": plan.endpoint, "cwd": os.getcwd(), "actor_ids": plan.cfg.actor_ids(),
               "argv": plan.argv, "started": started, "resumed": plan.resume, "part": part,
               "first_started": plan.previous.get("first_started", plan.previous.get("started", started)),
               "secure": plan.secure, "task_bounds": plan.bounds, **recipe_runtime(plan.cfg)}
    write_run_config(plan.run_dir, plan.cfg, runtime)
    # the learner builds its spaces from the task at once (instead of waiting for an actor to announce it), so it
    # is up before the actors step, as a learner of any task must be for a seeded run to repeat
    task_file = plan.run_dir / "learner" / TASK_FILE
    if plan.task is not None and not task_file.is_file():
        save_task(task_file, plan.task)
