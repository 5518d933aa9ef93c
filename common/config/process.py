"""How a process (learner, actor, human-input client) is configured: the run's settings, its run id, the router
endpoint and the Zenoh configuration file it connects with."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from khgrl.common.config.settings import RunConfig, add_config_flags, read_run_file, resolve
from khgrl.common.delivery.zenoh_config import ENV, config_file

__all__ = ["ProcessConfig", "add_process_flags", "resolve_process", "PROCESS_SETTINGS"]

# the settings every process has a flag for, whatever else it takes: how it reaches the router
PROCESS_SETTINGS = {"run", "connect", "connect_timeout", "lease_ms"}


@dataclass(frozen=True)
class ProcessConfig:
    """What a process (learner, actor, human-input client) runs with: the run's settings, its id (key prefix)
    and the router endpoint."""

    cfg: RunConfig
    run: str
    endpoint: str
    runtime: dict
    zenoh_config: str | None = None  # a Zenoh JSON5 file (--zenoh-config, else $ZENOH_CONFIG), None: built-in


def add_process_flags(parser: argparse.ArgumentParser, only: set[str] | None = None) -> None:
    """``--config`` (a run's ``config.json`` written by ``khgrl up``, or a TOML file), ``--run``, ``--connect``
    and the run-setting flags (``only``: those settings, and always :data:`PROCESS_SETTINGS`, so ``--connect-timeout``
    too): how every process is started (by ``khgrl up``: ``--config RUN_DIR/config.json``
    and its own id; by hand on another machine: flags)."""
    parser.add_argument("--config", default=None, metavar="FILE",
                        help="run configuration: RUN_DIR/config.json of khgrl up, or a TOML file (default: none)")
    parser.add_argument("--zenoh-config", default=None, metavar="FILE",
                        help=f"Zenoh configuration (JSON5; certificates, access, buffers) merged under KhGRL's "
                             f"required settings; examples in deploy/zenoh/ (default: ${ENV} if set, else built-in)")
    add_config_flags(parser, None if only is None else set(only) | PROCESS_SETTINGS)


def resolve_process(args: argparse.Namespace) -> ProcessConfig:
    """Settings < ``--config`` < flags. Run id: ``--run``, else the run file's, else ``run`` of the config;
    endpoint: ``--connect``, else the run file's router, else the default loopback router."""
    base = getattr(args, "config", None)
    runtime = read_run_file(base)[1] if base and str(base).endswith(".json") else {}
    cfg = resolve(base, args)
    run = getattr(args, "cfg__run", None) or runtime.get("run") or cfg.run
    if not run:
        raise ValueError("no run id: give --run RUN (printed by khgrl up) or --config RUN_DIR/config.json")
    endpoint = getattr(args, "cfg__connect", None) or runtime.get("endpoint") or cfg.connect or "tcp/127.0.0.1:7447"
    zenoh_config = config_file(getattr(args, "zenoh_config", None))
    return ProcessConfig(cfg=cfg, run=run, endpoint=endpoint, runtime=runtime, zenoh_config=zenoh_config)
