"""The learner's Zenoh side.

* :class:`LearnerLink` -- everything the learner declares: its inbox of transitions, control commands and the
  actors' checkpoint requests (subscribers filing into a bounded :class:`~khgrl.common.delivery.transport.Inbox`),
  the weights queryable, its task announcement and its liveliness token (named by its epoch).
* :class:`ZenohPublisher` -- the :class:`Publisher` the learner loop sends through: weights (published, and
  answered to queries), per-actor acks and status, each typed message encoded with this learner's id and a
  per-kind sequence number. The latest weights payload is kept for the weights queryable, so a late or restarted
  actor gets the current network at once. With the run's key (:mod:`~khgrl.common.delivery.run_key`) every ack
  and weights message carries its ``mac``.
* :func:`learner_alive` -- the live processes of a learner id (a second learner with that id refuses to start).
* :class:`ReplyBudget` -- what the weights queryable may answer: Zenoh tells a queryable nothing that identifies the
  querier (``source_info`` is empty unless the querier fills it in, and then it is whatever it says), so the budget
  is global: at most :data:`QUERY_RATE` replies a second (bursts of :data:`QUERY_BURST`) and
  :data:`QUERY_BYTES_PER_S` bytes of replies a second. A query over it is finalized without a reply (counted in
  ``queries_refused``, logged at a bounded rate). The answer is the bytes encoded when the weights were published:
  answering costs no encoding, and it runs on Zenoh's thread, never the training thread.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Protocol

from khgrl.common.delivery import data_keys
from khgrl.common.delivery.declare import alive_now, publisher, queryable, subscribe, token
from khgrl.common.delivery.task_link import TaskAnnouncer
from khgrl.common.delivery.transport import Inbox, undeclare_all
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.protocol import Ack, Keys, Status, Weights, encode

__all__ = ["Publisher", "ZenohPublisher", "LearnerLink", "ReplyBudget", "learner_alive", "INBOX_SIZE", "INBOX_BYTES",
           "QUERY_RATE", "QUERY_BURST", "QUERY_BYTES_PER_S"]

log = logging.getLogger("khgrl.learner")

# Transitions waiting to be ingested. When full, the newest are dropped ("drop_newest"): the actor keeps every
# batch until it is acknowledged and re-sends what was not, so a drop costs a re-send, never a transition.
INBOX_SIZE = 100_000
INBOX_BYTES = 256 * 2**20  # and at most this much payload (each actor has at most its window of batches out)
# The weights queryable's budget (an actor asks at start and then at most once a second while behind; every actor
# also gets each new version on the weights subscription).
QUERY_RATE = 20.0  # replies per second
QUERY_BURST = 40  # replies at once
QUERY_BYTES_PER_S = 64 * 2**20  # reply payload per second
REFUSED_LOG_EVERY_S = 10.0


class ReplyBudget:
    """Token buckets of replies and bytes (see the module docstring).

    :param rate: replies per second.
    :param burst: replies at once.
    :param bytes_per_s: reply payload per second (the bucket holds one second's worth, and at least one reply).
    :param clock: monotonic seconds.
    """

    def __init__(self, rate: float = QUERY_RATE, burst: int = QUERY_BURST, bytes_per_s: float = QUERY_BYTES_PER_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.rate, self.burst, self.bytes_per_s, self.clock = float(rate), float(burst), float(bytes_per_s), clock
        self._replies, self._bytes, self._t = self.burst, self.bytes_per_s, clock()
        self.refused = 0
        self._logged = (-float("inf"), 0)  # (when the last line was logged, refused then)

    def take(self, size: int) -> bool:
        """Whether a reply of ``size`` bytes may go now (then it is spent).

        :param size: the reply's payload bytes.
        """
        now = self.clock()
        dt, self._t = max(0.0, now - self._t), now
        self._replies = min(self.burst, self._replies + dt * self.rate)
        self._bytes = min(max(self.bytes_per_s, size), self._bytes + dt * self.bytes_per_s)
        if self._replies >= 1.0 and self._bytes >= size:
            self._replies -= 1.0
            self._bytes -= size
            return True
        self.refused += 1
        if now - self._logged[0] >= REFUSED_LOG_EVERY_S:
            log.warning("weights queries over the budget (%.0f/s, %.0f MB/s): %d refused since the last line "
                        "(%d in all)", self.rate, self.bytes_per_s / 1e6, self.refused - self._logged[1], self.refused)
            self._logged = (now, self.refused)
        return False


class Publisher(Protocol):
    """Where the learner loop's messages go (Zenoh in the process, a list in tests)."""

    queries: int  # weights queries answered so far

    def weights(self, msg: Weights) -> None: ...

    def ack(self, msg: Ack) -> None: ...

    def status(self, msg: Status) -> None: ...


class ZenohPublisher:
    """Publishers of one learner; :meth:`answer` is the weights queryable's handler."""

    def __init__(self, session: Any, keys: Keys, sender: str, key: data_keys.Keyish = None) -> None:
        """:param session: an open Zenoh session
        :param keys: the run's key expressions
        :param sender: this learner's id (envelope ``sender``)
        :param key: the run's key: acks and weights carry a ``mac`` (None: they do not)
        """
        self.session, self.keys, self.sender, self.key = session, keys, sender, key
        self.weights_pub = publisher(session, keys.weights, congestion="block", priority="data")
        self.status_pub = publisher(session, keys.status("learner", sender), congestion="drop", priority="data_low")
        self.ack_pubs: dict[str, Any] = {}
        self.seq = {"weights": 0, "ack": 0, "status": 0}
        self.queries = 0
        self.budget = ReplyBudget()
        self._latest = b""
        self._lock = threading.Lock()
        self._seq_lock = threading.Lock()  # the ingest and training threads both publish

    def _encode(self, msg: Any) -> bytes:
        """``msg`` as a payload from this learner, numbered per kind."""
        with self._seq_lock:
            seq = self.seq[msg.KIND]
            self.seq[msg.KIND] += 1
        return encode(msg, self.sender, seq)

    def weights(self, msg: Weights) -> None:
        """Publish new weights (and keep them for queries).

        :param msg: the weights
        """
        blob = self._encode(data_keys.sign(msg, self.key))
        with self._lock:
            self._latest = blob
        self.weights_pub.put(blob)

    def ack(self, msg: Ack) -> None:
        """Publish an ack on its actor's key (the publisher is declared on first use).

        :param msg: the ack
        """
        with self._seq_lock:
            pub = self.ack_pubs.get(msg.actor)
            if pub is None:
                pub = self.ack_pubs[msg.actor] = publisher(self.session, self.keys.ack(msg.actor), congestion="block",
                                                           priority="interactive_low")
        pub.put(self._encode(data_keys.sign(msg, self.key)))

    def status(self, msg: Status) -> None:
        """Publish a status (dropped under congestion: the next one follows in a second).

        :param msg: the status
        """
        self.status_pub.put(self._encode(msg))

    @property
    def queries_refused(self) -> int:
        """Weights queries refused over the reply budget."""
        return self.budget.refused

    def answer(self, query: Any) -> None:
        """Reply to a weights query with the latest weights, as encoded when they were published (nothing before
        the first; nothing over the :class:`ReplyBudget`); always finalizes.

        :param query: the Zenoh query
        """
        with query:
            with self._lock:
                blob = self._latest
                ok = bool(blob) and self.budget.take(len(blob))
            if ok:
                query.reply(self.keys.weights, blob)
                self.queries += 1

    def close(self) -> None:
        """Undeclare every publisher (best effort, on the way out)."""
        undeclare_all(self.weights_pub, self.status_pub, *self.ack_pubs.values())


class LearnerLink:
    """Everything one learner declares on its session (in the order the protocol expects: the task, subscribers and
    the weights queryable, then -- :meth:`announce` -- the liveliness token).

    :param session: an open Zenoh session
    :param keys: the run's key expressions
    :param learner_id: this learner's id
    :param task: the run's task descriptor (announced on ``task/learner/<id>``)
    :param key: the run's key (acks and weights carry a ``mac``; None: they do not)
    """

    def __init__(self, session: Any, keys: Keys, learner_id: str, task: TaskDescriptor,
                 key: data_keys.Keyish = None) -> None:
        self.session, self.keys, self.id = session, keys, learner_id
        self.announcer = TaskAnnouncer(session, keys, "learner", learner_id, task)
        self.publisher = ZenohPublisher(session, keys, learner_id, key)
        self.inbox = Inbox(maxsize=INBOX_SIZE, overflow="drop_newest", max_bytes=INBOX_BYTES)
        cb = self.inbox.callback
        self.decls = [subscribe(session, keys.transitions("*"), cb("transitions")),
                      subscribe(session, keys.control("learner"), cb("control")),
                      subscribe(session, keys.control("all"), cb("control")),
                      subscribe(session, keys.request("*"), cb("request")),  # the actors' checkpoint requests
                      queryable(session, keys.weights, self.publisher.answer)]

    def announce(self, epoch: str) -> None:
        """Declare the liveliness token: it names this incarnation (its epoch), and actors take weights only of an
        epoch whose token is alive.

        :param epoch: this learner incarnation's epoch
        """
        self.decls.append(token(self.session, self.keys.learner_alive(self.id, epoch)))

    def close(self) -> None:
        """Undeclare everything (best effort, on the way out)."""
        undeclare_all(*self.decls)
        self.announcer.undeclare()
        self.publisher.close()


def learner_alive(session: Any, keys: Keys, learner_id: str, timeout: float = 1.0) -> list[str]:
    """The liveliness keys ``alive/learner/<id>/*`` alive on the router now (empty: none, or the query failed).

    :param session: an open Zenoh session
    :param keys: the run's key expressions
    :param learner_id: the learner id
    :param timeout: seconds to wait for replies
    """
    try:
        return sorted(alive_now(session, keys.learner_alive(learner_id, "**"), timeout))
    except Exception:  # noqa: BLE001 - no answer is no learner
        return []
