"""Zenoh sessions for KhGRL processes (zenoh-python 1.x; see ../shared/design/zenoh-notes.md).

Topology: one small router process (zenoh-python in router mode, no other binary) listens on loopback;
the learner, actors and human-input clients connect to it as clients, with retry, so any of them can
start first and a restarted router is rejoined automatically. Multicast scouting is always off and every
endpoint explicit. ``--connect tcp/HOST:PORT`` points a process at a router on another machine.

Rules the processes follow (measured pitfalls): one session per process opened in ``main()`` inside a
``with`` block (a callback subscriber left open hangs interpreter exit); processes are spawned, never forked
after ``zenoh.open()``; every ``get`` has a timeout; callbacks only hand data to Python queues.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import socket
import sys
import threading
import time

__all__ = ["client_config", "router_config", "free_port", "open_client", "install_stop_handlers", "router_main",
           "setup_process_logging"]

log = logging.getLogger("khgrl.session")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def _base_config(mode: str, listen: list[str], connect: list[str], lease_ms: int):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false" if mode == "client" else "true")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("transport/link/tx/lease", str(int(lease_ms)))
    # a learner pausing to checkpoint must not get its link killed by BLOCK publishers (default 5 s)
    conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close", "60000000")
    # keep queries/replies off shared memory (zenoh#2628: SHM can drop queries when an RX thread stalls)
    conf.insert_json5("transport/shared_memory/enabled", "false")
    return conf


def client_config(connect: str = DEFAULT_ENDPOINT, lease_ms: int = 3000):
    """A client that waits for (and re-joins) the router at ``connect``."""
    conf = _base_config("client", [], [connect], lease_ms)
    conf.insert_json5("connect/timeout_ms", "-1")
    conf.insert_json5("connect/retry", "{period_init_ms: 100, period_max_ms: 1000, period_increase_factor: 2}")
    return conf


def router_config(listen: str = DEFAULT_ENDPOINT, lease_ms: int = 3000):
    return _base_config("router", [listen], [], lease_ms)


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (bind to port 0 and read it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_client(connect: str, lease_ms: int = 3000):
    import zenoh

    zenoh.init_log_from_env_or("error")
    return zenoh.open(client_config(connect, lease_ms))


class StopFlag:
    """Set by SIGINT/SIGTERM; long loops poll it and exit their ``with zenoh.open(...)`` block cleanly."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reason = ""

    def set(self, reason: str = "stop") -> None:
        self.reason = self.reason or reason
        self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float) -> bool:
        return self.event.wait(timeout)


def install_stop_handlers(flag: StopFlag) -> None:
    """SIGINT and SIGTERM set ``flag`` (a second signal exits hard)."""

    def handler(signum, _frame):
        if flag:
            sys.exit(128 + signum)
        flag.set(signal.Signals(signum).name)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def router_main(argv: list[str] | None = None) -> int:
    """``khgrl router``: a zenoh router on loopback (or any listen endpoint) until SIGINT/SIGTERM."""
    import zenoh

    parser = argparse.ArgumentParser(prog="khgrl router", description="Run a Zenoh router for KhGRL processes.")
    parser.add_argument("--listen", default=DEFAULT_ENDPOINT, help="endpoint to listen on (default %(default)s)")
    parser.add_argument("--lease-ms", type=int, default=3000)
    args = parser.parse_args(argv)
    flag = StopFlag()
    install_stop_handlers(flag)
    zenoh.init_log_from_env_or("error")
    with zenoh.open(router_config(args.listen, args.lease_ms)) as session:
        print(f"khgrl router {session.zid()} listening on {args.listen}", flush=True)
        while not flag.wait(0.2):
            pass
    return 0


def sleep_until(deadline: float) -> None:
    delay = deadline - time.perf_counter()
    if delay > 0:
        time.sleep(delay)


def setup_process_logging(log_path) -> None:
    """Log INFO and above to ``log_path`` and stdout (the launcher captures stdout in RUN_DIR/logs/)."""
    from pathlib import Path

    fmt = logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s")
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    for h in (logging.FileHandler(Path(log_path)), logging.StreamHandler(sys.stdout)):
        h.setFormatter(fmt)
        root.addHandler(h)
