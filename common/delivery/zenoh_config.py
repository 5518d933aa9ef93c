"""Zenoh configurations for KhGRL processes: a user's configuration file (Zenoh's own JSON5 format, given with
``--zenoh-config FILE`` or the ``ZENOH_CONFIG`` environment variable) with KhGRL's required settings merged over it.

What KhGRL always sets (a different value in the file is reported as a conflict, and KhGRL's wins):

* ``mode`` (``client`` for the learner, actors and input clients; ``router`` for ``khgrl router``),
* ``listen/endpoints`` and ``connect/endpoints`` (from ``--listen`` / ``--connect``: one explicit endpoint),
* ``scouting/multicast/enabled: false`` (and gossip off for clients): nothing is discovered, everything is named.

What KhGRL tunes only where the file leaves Zenoh's default (the file wins; a value equal to Zenoh's default counts
as left): the link lease, the time a BLOCK publisher waits before closing a stalled link (clients 60 s, the router
2 s), shared memory off (the whole ``transport/shared_memory`` section: a file that sets anything in it keeps its
own; ``deploy/zenoh/shared-memory.json5`` turns it on for puts), the largest message, the client's connect retry.

Everything else -- TLS certificates (``transport/link/tls``), user/password authentication, access control, buffer
sizes -- comes from the file untouched. The shipped examples are in ``deploy/zenoh/``.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

__all__ = ["ENV", "MAX_MESSAGE_BYTES", "ZenohConfigError", "build_config", "config_file", "identity"]

log = logging.getLogger("khgrl.transport")

ENV = "ZENOH_CONFIG"
# the largest message any process accepts (the weights' 64 MiB limit, plus slack for the envelope): Zenoh drops a
# larger (fragmented) message at the link before it is reassembled, and an Inbox drops one before copying it
MAX_MESSAGE_BYTES = 68 * 1024 * 1024
SHM = "transport/shared_memory"  # Zenoh's shared memory between processes of one host (one section: _tuned)


class ZenohConfigError(ValueError):
    """A Zenoh configuration file that cannot be used (missing, not JSON5, unknown keys, TLS without certificates)."""


def config_file(path: str | os.PathLike | None = None) -> str | None:
    """The configuration file a process uses: ``path`` (``--zenoh-config``) if given, else ``$ZENOH_CONFIG`` if set,
    else None (KhGRL's built-in settings only).

    :param path: the ``--zenoh-config`` value, or None
    """
    chosen = path if path else os.environ.get(ENV) or None
    return str(chosen) if chosen else None


def _tuned(mode: str, lease_ms: int, default_shm: dict[str, Any]) -> dict[str, Any]:
    tuned: dict[str, Any] = {
        "transport/link/tx/lease": int(lease_ms),
        # clients: a learner pausing to checkpoint must not get its link killed by BLOCK publishers (default 5 s).
        # The router: a client that stops reading (its link down, its process stopped) must not freeze the router
        # for everyone -- forwarding BLOCK messages to it blocks (zenoh#1876); after 2 s its link is closed, it
        # reconnects by itself and its stream re-sends what is missing (tests/integration/test_netns.py)
        "transport/link/tx/queue/congestion_control/block/wait_before_close": 2_000_000 if mode == "router"
        else 60_000_000,
        # shared memory off, as one section: a file that sets anything in it keeps its own (deploy/zenoh/
        # shared-memory.json5 turns it on for puts only: zenoh#2628, SHM can drop queries when an RX thread stalls)
        SHM: {**default_shm, "enabled": False},
        "transport/link/rx/max_message_size": MAX_MESSAGE_BYTES,
    }
    if mode == "client":  # wait for (and re-join) the router
        tuned["connect/timeout_ms"] = -1
        tuned["connect/retry"] = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}
    return tuned


def _load(path: str):
    import zenoh

    if not Path(path).is_file():
        raise ZenohConfigError(f"Zenoh configuration {path} does not exist")
    try:
        return zenoh.Config.from_file(path)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError: a parse or schema error, reported as one line
        first = " ".join(str(exc).split())
        raise ZenohConfigError(f"Zenoh configuration {path} cannot be read: {first}") from None


def _get(conf, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - a key this Zenoh version does not know
        return None


def build_config(mode: str, listen: list[str], connect: list[str], lease_ms: int = 3000,
                 file: str | os.PathLike | None = None):
    """A ``zenoh.Config``: ``file`` (if any) with KhGRL's settings merged over it (module docstring).

    :param mode: ``client`` or ``router``
    :param listen: endpoints to listen on
    :param connect: endpoints to connect to
    :param lease_ms: link lease (used where the file leaves the default)
    :param file: a Zenoh JSON5 configuration file, or None
    :returns: the configuration; conflicts with the file are logged as warnings
    :raises ZenohConfigError: the file cannot be used
    """
    import zenoh

    conf = _load(str(file)) if file else zenoh.Config()
    default = zenoh.Config()
    required: dict[str, Any] = {"mode": mode, "listen/endpoints": list(listen), "connect/endpoints": list(connect),
                                "scouting/multicast/enabled": False,
                                "scouting/gossip/enabled": mode != "client"}
    for key, ours in required.items():
        theirs = _get(conf, key)
        if file and theirs not in (ours, _get(default, key)):
            log.warning("Zenoh configuration %s sets %s = %s; KhGRL uses %s (its required setting)", file, key,
                        json.dumps(theirs), json.dumps(ours))
        conf.insert_json5(key, json.dumps(ours))
    for key, ours in _tuned(mode, lease_ms, _get(default, SHM)).items():
        if _get(conf, key) == _get(default, key):
            conf.insert_json5(key, json.dumps(ours))
    _check_shared_memory(conf, file)
    _check_tls(conf, listen + connect, file)
    return conf


def _check_shared_memory(conf, file) -> None:
    """A file that turns shared memory on for queries or replies too: say what that risks (zenoh#2628)."""
    shm = _get(conf, SHM) or {}
    opt = shm.get("transport_optimization") or {}
    risky = sorted({"query", "reply"} & set(opt.get("messages") or []))
    if shm.get("enabled") and opt.get("enabled") and risky:
        log.warning("Zenoh configuration %s puts %s on shared memory: a stalled receiver can drop them (zenoh#2628); "
                    "deploy/zenoh/shared-memory.json5 keeps them off (messages: [\"put\"])", file, " and ".join(risky))


def _check_tls(conf, endpoints: list[str], file) -> None:
    """A ``tls/`` endpoint needs certificates: say so before Zenoh fails with a less helpful message."""
    if not any(e.startswith(("tls/", "quic/")) for e in endpoints):
        return
    tls = _get(conf, "transport/link/tls") or {}
    if not tls.get("root_ca_certificate"):
        where = f"the Zenoh configuration {file} has none" if file else "no Zenoh configuration file was given"
        raise ZenohConfigError(
            f"a tls/ endpoint needs certificates in transport/link/tls (root_ca_certificate, and with mutual TLS "
            f"the process's own certificate and key), but {where}. Give --zenoh-config FILE (examples in "
            f"deploy/zenoh/; make certificates with `khgrl certs`)")


def identity(conf) -> str:
    """Who this configuration makes the process on the network, for its log: the common name of its TLS
    certificate (the subject the router's access control knows it by), or that it has none.

    :param conf: a ``zenoh.Config``
    """
    tls = _get(conf, "transport/link/tls") or {}
    cert = tls.get("connect_certificate") or tls.get("listen_certificate")
    if not cert:
        return "no certificate (plain, unauthenticated)"
    try:
        from cryptography import x509
        from cryptography.x509.oid import NameOID

        c = x509.load_pem_x509_certificate(Path(cert).read_bytes())
        names = c.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        cn = str(names[0].value) if names else "?"
    except Exception as exc:  # noqa: BLE001 - zenoh itself reports an unusable certificate when it opens
        return f"certificate {cert} (unreadable: {exc})"
    mtls = " (mutual TLS)" if tls.get("enable_mtls") else ""
    return f"{cn}{mtls}, certificate {cert}"
