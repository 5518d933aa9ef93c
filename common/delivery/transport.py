"""Zenoh for KhGRL processes (zenoh-python 1.x): configurations,
opening a session that can be interrupted, and the one inbox pattern (callback -> bounded queue).

Topology: one small router process (``khgrl router``) listens on loopback; the learner, actors and human-input
clients connect to it as clients, with retry, so any of them can start first and a restarted router is
rejoined automatically. Multicast scouting is always off and every endpoint explicit.

Rules every process follows (measured pitfalls): one session per process, opened in ``main()`` and closed with
a ``with`` block (a callback subscriber left open hangs interpreter exit); processes are spawned, never forked
after ``zenoh.open()``; every ``get`` has a timeout; callbacks only hand bytes to an :class:`Inbox`.

One module of ~330 lines on purpose: everything that opens a Zenoh session (configurations, interruptible open, the
inbox) in one place.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time
from typing import Any, Callable

from khgrl.common.delivery.zenoh_config import MAX_MESSAGE_BYTES, ZenohConfigError, build_config, config_file, identity

__all__ = ["DEFAULT_ENDPOINT", "MAX_MESSAGE_BYTES", "client_config", "router_config", "free_port", "open_client",
           "open_router", "wait_reachable", "Inbox", "Rings", "undeclare_all", "endpoint_host_port"]

log = logging.getLogger("khgrl.transport")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def client_config(connect: str = DEFAULT_ENDPOINT, lease_ms: int = 3000, file: str | None = None):
    """A client that waits for (and re-joins) the router at ``connect``; ``file``: a Zenoh configuration merged
    under KhGRL's settings (:mod:`khgrl.common.delivery.zenoh_config`)."""
    return build_config("client", [], [connect], lease_ms, file)


def router_config(listen: str = DEFAULT_ENDPOINT, lease_ms: int = 3000, file: str | None = None):
    """A router listening on ``listen``; ``file`` as in :func:`client_config`."""
    return build_config("router", [listen], [], lease_ms, file)


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (bind to port 0 and read it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint_host_port(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of a ``tcp/``, ``tls/`` or ``quic/`` endpoint; None for other kinds."""
    proto, _, addr = endpoint.partition("/")
    if proto not in ("tcp", "tls", "quic") or ":" not in addr:
        return None
    host, _, port = addr.split("#")[0].rpartition(":")
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        return None


def wait_reachable(endpoint: str, timeout: float, stop: Callable[[], bool] = lambda: False) -> None:
    """Return once something accepts TCP connections at ``endpoint``; :class:`ConnectionError` naming it after
    ``timeout`` s (or at once if ``stop()`` turns true). Endpoints that are not TCP-based are not probed."""
    hp = endpoint_host_port(endpoint)
    if hp is None:
        return
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection(hp, timeout=0.5):
                return
        except OSError as exc:
            last = exc
        if stop():
            raise ConnectionError(f"stopped while waiting for the Zenoh router at {endpoint}")
        if time.monotonic() > deadline:
            raise ConnectionError(f"no Zenoh router reachable at {endpoint} within {timeout:g} s ({last})")
        time.sleep(0.2)


class ConnectTimeout(ConnectionError):
    """No session within the connect timeout."""


def _open(conf, stop: Callable[[], bool], timeout: float | None, what: str):
    """``zenoh.open(conf)`` in a helper thread, so that this thread keeps handling signals (a stop request or
    Ctrl-C while Zenoh waits for a router) and can give up after ``timeout`` s."""
    import zenoh

    zenoh.init_log_from_env_or("error")
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["session"] = zenoh.open(conf)
        except Exception as exc:  # noqa: BLE001 - reported to the caller
            box["error"] = exc

    th = threading.Thread(target=target, name="zenoh-open", daemon=True)
    th.start()
    deadline = None if timeout is None else time.monotonic() + timeout
    while th.is_alive():
        th.join(0.1)
        if th.is_alive() and (stop() or (deadline is not None and time.monotonic() > deadline)):
            if stop():
                raise ConnectionError(f"stopped while opening a Zenoh session ({what})")
            raise ConnectTimeout(f"not connected within {timeout:g} s while opening a Zenoh session ({what})")
    if "error" in box:
        raise ConnectionError(f"could not open a Zenoh session ({what}): {box['error']}")
    return box["session"]


def _configured(make: Callable, endpoint: str, lease_ms: int, zenoh_config: str | None):
    """``make(endpoint, lease_ms, file)`` with the file chosen by
    :func:`~khgrl.common.delivery.zenoh_config.config_file`; the
    identity it gives the process is logged; an unusable file is a :class:`ConnectionError` naming it."""
    file = config_file(zenoh_config)
    try:
        conf = make(endpoint, lease_ms, file)
    except ZenohConfigError as exc:
        raise ConnectionError(str(exc)) from None
    log.info("Zenoh: %s%s; identity: %s", endpoint, f" (configuration {file})" if file else "", identity(conf))
    return conf


def open_client(connect: str, lease_ms: int = 3000, *, stop: Callable[[], bool] = lambda: False,
                timeout: float | None = None, zenoh_config: str | None = None):
    """A client session to the router at ``connect`` (use it as a context manager). Waits for the router
    (it may start later) for ``timeout`` s (None: without end), then raises :class:`ConnectionError` with one line
    naming the endpoint; returns early with :class:`ConnectionError` when ``stop()`` turns true (e.g. a process's
    stop flag set by SIGTERM).

    :param connect: the router's endpoint
    :param lease_ms: the link lease
    :param stop: polled while waiting
    :param timeout: seconds to wait for the router (every process: ``--connect-timeout``)
    :param zenoh_config: a Zenoh configuration file (``--zenoh-config``); None: ``$ZENOH_CONFIG`` if set
    """
    conf = _configured(client_config, connect, lease_ms, zenoh_config)
    try:
        return _open(conf, stop, timeout, f"router {connect}")
    except ConnectTimeout:
        raise ConnectionError(
            f"no connection to the Zenoh router at {connect} within {timeout:g} s (--connect-timeout): is a router "
            f"running there, and does it speak {connect.partition('/')[0]}/ (a tls/ router needs a tls/ endpoint "
            f"and certificates: --zenoh-config)?") from None


def open_router(listen: str, lease_ms: int = 3000, zenoh_config: str | None = None):
    """A router session listening on ``listen``; ``zenoh_config`` as in :func:`open_client`."""
    conf = _configured(router_config, listen, lease_ms, zenoh_config)
    return _open(conf, lambda: False, 30.0, f"router listening on {listen}")


class Inbox:
    """Zenoh callbacks put ``(kind, key, payload bytes, arrival)`` here and return at once; the process's own
    loop takes them out. Bounded: when ``maxsize`` items wait, the overflow policy decides --
    ``"drop_oldest"`` (keep the newest: frames, corrections) or ``"drop_newest"`` (keep what came first:
    a stream whose sender re-sends what was not acknowledged). Dropped items are counted by kind. A payload
    larger than its kind's limit is dropped in the callback before it is copied out of Zenoh (counted in
    ``oversize``)."""

    POLICIES = ("drop_oldest", "drop_newest")

    def __init__(self, maxsize: int = 10_000, overflow: str = "drop_oldest", max_bytes: int | None = None) -> None:
        """:param maxsize: items waiting at most
        :param overflow: what goes when it is full: ``drop_oldest`` or ``drop_newest``
        :param max_bytes: payload bytes waiting at most (None: no byte bound), so that memory stays bounded
            whatever the size of the messages
        """
        if overflow not in self.POLICIES:
            raise ValueError(f"overflow policy must be one of {self.POLICIES}")
        self.q: queue.Queue = queue.Queue(maxsize=maxsize)
        self.overflow = overflow
        self.max_bytes = max_bytes
        self.bytes = 0  # payload bytes waiting
        self.dropped: dict[str, int] = {}
        self.oversize: dict[str, int] = {}
        # kind -> ``gate(key, size)``: whether a sample may be copied out of Zenoh and filed (the learner's
        # per-sender budget, :class:`~khgrl.common.delivery.admission.Admission`); it counts what it refuses
        self.gates: dict[str, Callable[[str, int], bool]] = {}
        self._lock = threading.Lock()

    @staticmethod
    def _size(item: tuple) -> int:
        return len(item[2]) if isinstance(item[2], (bytes, bytearray)) else 0

    def put(self, item: tuple) -> None:
        """File ``item`` (``(kind, key, payload, arrival)``), or drop by the overflow policy when full."""
        n = self._size(item)
        with self._lock:
            if self.max_bytes is None or self.bytes + n <= self.max_bytes:
                try:
                    self.q.put_nowait(item)
                    self.bytes += n
                    return
                except queue.Full:
                    pass
            self.dropped[item[0]] = self.dropped.get(item[0], 0) + 1
            if self.overflow == "drop_newest":
                return
            while self.q.full() or (self.max_bytes is not None and self.bytes + n > self.max_bytes and self.q.qsize()):
                try:
                    self.bytes -= self._size(self.q.get_nowait())
                except queue.Empty:
                    break
            if self.max_bytes is None or self.bytes + n <= self.max_bytes:
                try:
                    self.q.put_nowait(item)
                    self.bytes += n
                except queue.Full:
                    pass

    def callback(self, kind: str, max_bytes: int = MAX_MESSAGE_BYTES) -> Callable:
        """A Zenoh sample callback that files samples under ``kind``.

        :param kind: the name items are filed under
        :param max_bytes: larger payloads are counted in ``oversize`` and dropped without being copied
        """

        def cb(sample) -> None:
            size = len(sample.payload)
            if size > max_bytes:
                with self._lock:
                    self.oversize[kind] = self.oversize.get(kind, 0) + 1
                return
            key, gate = str(sample.key_expr), self.gates.get(kind)
            if gate is not None and not gate(key, size):
                return
            self.put((kind, key, sample.payload.to_bytes(), time.monotonic()))

        return cb

    def liveliness_callback(self, kind: str = "alive") -> Callable:
        """A liveliness subscriber callback: ``(kind, key, appeared: bool, arrival)``."""
        import zenoh

        def cb(sample) -> None:
            self.put((kind, str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, time.monotonic()))

        return cb

    def get(self, timeout: float = 0.0) -> tuple | None:
        """The next item, waiting up to ``timeout`` s (0: don't wait); None if there is none."""
        try:
            item = self.q.get(timeout=timeout) if timeout > 0 else self.q.get_nowait()
        except queue.Empty:
            return None
        n = self._size(item)
        if n:
            with self._lock:
                self.bytes -= n
        return item

    def qsize(self) -> int:
        return self.q.qsize()


class Rings:
    """Subscribers whose samples wait in Zenoh's own ring buffers (``RingChannel``: the newest ``capacity`` kept,
    older ones dropped without a trace) until the owner's loop polls them: no Python callback runs per sample, so a
    flood on these keys costs the loop no time and no GIL (with callbacks, 100,000 messages in a second stalled a
    50 Hz loop for 200 ms). For keys where the newest messages matter (acks carry cumulative counts; corrections
    and commands are re-sent or superseded). A payload over its kind's limit is counted in ``oversize``, reported
    to ``on_oversize`` and skipped without being copied.

    :param session: the open Zenoh session
    :param on_oversize: called with ``(kind, key, size, limit)`` for each payload over its limit (e.g. to count it
        as a rejected message)
    """

    def __init__(self, session, on_oversize: Callable[[str, str, int, int], None] | None = None) -> None:
        self.session = session
        self.subs: list[tuple[str, Any, int]] = []  # (kind, subscriber, max bytes)
        self.oversize: dict[str, int] = {}
        self.on_oversize = on_oversize

    def add(self, kind: str, key: str, capacity: int, max_bytes: int = MAX_MESSAGE_BYTES) -> None:
        """Subscribe ``key``, its samples filed under ``kind``.

        :param kind: the name items are filed under
        :param key: the key expression
        :param capacity: samples kept at most (the oldest go first)
        :param max_bytes: larger payloads are counted in ``oversize`` and skipped
        """
        import zenoh

        self.subs.append((kind, self.session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity)), max_bytes))

    def poll(self, limit: int) -> list[tuple]:
        """Up to ``limit`` items ``(kind, key, payload bytes, arrival)``, taking one from each subscriber in turn
        (a flood on one key cannot starve the others).

        :param limit: items at most
        """
        out: list[tuple] = []
        live = list(self.subs)
        while live and len(out) < limit:
            for entry in list(live):
                kind, sub, max_bytes = entry
                sample = sub.try_recv()
                if sample is None:
                    live.remove(entry)
                elif len(sample.payload) > max_bytes:
                    self.oversize[kind] = self.oversize.get(kind, 0) + 1
                    if self.on_oversize is not None:
                        self.on_oversize(kind, str(sample.key_expr), len(sample.payload), max_bytes)
                else:
                    out.append((kind, str(sample.key_expr), sample.payload.to_bytes(), time.monotonic()))
                if len(out) >= limit:
                    break
        return out

    def undeclare(self) -> None:
        """Undeclare every subscriber (best effort)."""
        undeclare_all(*(sub for _, sub, _ in self.subs))


def undeclare_all(*decls) -> None:
    """Undeclare publishers, subscribers, queryables and tokens, best effort (on the way out)."""
    for d in decls:
        try:
            d.undeclare()
        except Exception:  # noqa: BLE001 - a session already closing
            pass
