"""Declarations and calls on an open Zenoh session, with Zenoh's quality-of-service named in words: the one place,
with :mod:`khgrl.common.delivery.transport`, that imports ``zenoh`` for a running process (the router and the
configuration files aside: :data:`khgrl.common.delivery.ZENOH_MODULES`). The actor, learner, human-input and
launcher links (:mod:`~khgrl.common.delivery.actor_link`, :mod:`~khgrl.common.delivery.learner_link`,
:mod:`~khgrl.common.delivery.human_link`) and the benchmarks declare through these.

Congestion control: ``block`` (the publisher waits: nothing is dropped under congestion) or ``drop`` (dropped under
congestion: frames, status). Priority: ``interactive_high``, ``interactive_low``, ``data``, ``data_low`` or None
(Zenoh's default). A call given none of them passes none to Zenoh (its defaults).
"""

from __future__ import annotations

from typing import Any, Callable

__all__ = ["publisher", "put", "subscribe", "ring_subscriber", "alive_subscriber", "queryable", "token", "query",
           "alive_now"]


def _qos(congestion: str | None, priority: str | None, express: bool | None) -> dict[str, Any]:
    """Zenoh's keyword arguments for the QoS given in words (only those given)."""
    import zenoh

    kw: dict[str, Any] = {}
    if congestion is not None:
        kw["congestion_control"] = {"block": zenoh.CongestionControl.BLOCK,
                                    "drop": zenoh.CongestionControl.DROP}[congestion]
    if priority is not None:
        kw["priority"] = getattr(zenoh.Priority, priority.upper())
    if express is not None:
        kw["express"] = express
    return kw


def publisher(session: Any, key: str, *, congestion: str | None = None, priority: str | None = None,
              express: bool | None = None) -> Any:
    """A publisher on ``key`` (``.put(payload)``, ``.undeclare()``).

    :param session: an open Zenoh session
    :param key: the key expression
    :param congestion: ``block`` or ``drop`` (None: Zenoh's default)
    :param priority: ``interactive_high``, ``interactive_low``, ``data``, ``data_low`` (None: Zenoh's default)
    :param express: send at once without batching (None: Zenoh's default)
    """
    return session.declare_publisher(key, **_qos(congestion, priority, express))


def put(session: Any, key: str, payload: bytes, *, congestion: str | None = None, priority: str | None = None,
        express: bool | None = None) -> None:
    """One payload on ``key`` without a declared publisher; QoS as in :func:`publisher`.

    :param session: an open Zenoh session
    :param key: the key expression
    :param payload: the bytes
    """
    session.put(key, payload, **_qos(congestion, priority, express))


def subscribe(session: Any, key: str, callback: Callable, *, remote_only: bool = False) -> Any:
    """A subscriber calling ``callback(sample)`` (e.g. :meth:`~khgrl.common.delivery.transport.Inbox.callback`).

    :param session: an open Zenoh session
    :param key: the key expression
    :param callback: called with each sample, on a Zenoh thread
    :param remote_only: only samples from other sessions (not this process's own puts)
    """
    if not remote_only:
        return session.declare_subscriber(key, callback)
    import zenoh

    return session.declare_subscriber(key, callback, allowed_origin=zenoh.Locality.REMOTE)


def ring_subscriber(session: Any, key: str, capacity: int) -> Any:
    """A subscriber whose samples wait in Zenoh's ring buffer (the newest ``capacity`` kept), read with
    ``.try_recv()``.

    :param session: an open Zenoh session
    :param key: the key expression
    :param capacity: samples kept at most
    """
    import zenoh

    return session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity))


def alive_subscriber(session: Any, key: str, callback: Callable, *, history: bool = True) -> Any:
    """A liveliness subscriber (tokens appearing and disappearing; with ``history``, those alive already too).

    :param session: an open Zenoh session
    :param key: the liveliness key expression
    :param callback: e.g. :meth:`~khgrl.common.delivery.transport.Inbox.liveliness_callback`
    :param history: also report the tokens alive when it is declared
    """
    return session.liveliness().declare_subscriber(key, callback, history=history)


def queryable(session: Any, key: str, handler: Callable) -> Any:
    """A queryable answering on ``key`` with ``handler(query)`` (which replies and finalizes the query).

    :param session: an open Zenoh session
    :param key: the key expression
    :param handler: called with each query, on a Zenoh thread
    """
    return session.declare_queryable(key, handler)


def token(session: Any, key: str) -> Any:
    """A liveliness token on ``key`` (``.undeclare()``).

    :param session: an open Zenoh session
    :param key: the key expression
    """
    return session.liveliness().declare_token(key)


def query(session: Any, key: str, timeout: float) -> list[tuple[str, bytes]]:
    """``(key, payload)`` of every answer to a query on ``key`` within ``timeout`` s (errors skipped).

    :param session: an open Zenoh session
    :param key: the key expression
    :param timeout: seconds to wait for answers
    """
    return [(str(r.ok.key_expr), r.ok.payload.to_bytes()) for r in session.get(key, timeout=timeout) if r.ok]


def alive_now(session: Any, key: str, timeout: float) -> list[str]:
    """The liveliness keys alive now under ``key`` (a liveliness query), in the order they answered.

    :param session: an open Zenoh session
    :param key: the liveliness key expression
    :param timeout: seconds to wait for answers
    """
    return [str(r.ok.key_expr) for r in session.liveliness().get(key, timeout=timeout) if r.ok]
