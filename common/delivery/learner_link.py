"""The learner's Zenoh output: weights (published, and answered to queries), per-actor acks and status.

Implements the :class:`khgrl.learner.loop.Publisher` interface over a Zenoh session: each typed message is encoded
with this learner's id and a per-kind sequence number. The latest weights payload is kept for the weights
queryable, so a late or restarted actor gets the current network at once.
"""

from __future__ import annotations

import threading
from typing import Any

from khgrl.common.delivery.transport import undeclare_all
from khgrl.common.wire.protocol import Ack, Keys, Status, Weights, encode

__all__ = ["ZenohPublisher"]


class ZenohPublisher:
    """Publishers of one learner; :meth:`answer` is the weights queryable's handler."""

    def __init__(self, session: Any, keys: Keys, sender: str) -> None:
        """:param session: an open Zenoh session
        :param keys: the run's key expressions
        :param sender: this learner's id (envelope ``sender``)
        """
        import zenoh

        self._zenoh = zenoh
        self.session, self.keys, self.sender = session, keys, sender
        self.weights_pub = session.declare_publisher(keys.weights, congestion_control=zenoh.CongestionControl.BLOCK,
                                                     priority=zenoh.Priority.DATA)
        self.status_pub = session.declare_publisher(keys.status("learner", sender),
                                                    congestion_control=zenoh.CongestionControl.DROP,
                                                    priority=zenoh.Priority.DATA_LOW)
        self.ack_pubs: dict[str, Any] = {}
        self.seq = {"weights": 0, "ack": 0, "status": 0}
        self.queries = 0
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
        blob = self._encode(msg)
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
                zenoh = self._zenoh
                pub = self.ack_pubs[msg.actor] = self.session.declare_publisher(
                    self.keys.ack(msg.actor), congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.INTERACTIVE_LOW)
        pub.put(self._encode(msg))

    def status(self, msg: Status) -> None:
        """Publish a status (dropped under congestion: the next one follows in a second).

        :param msg: the status
        """
        self.status_pub.put(self._encode(msg))

    def answer(self, query: Any) -> None:
        """Reply to a weights query with the latest weights (nothing before the first); always finalizes.

        :param query: the Zenoh query
        """
        with query:
            with self._lock:
                blob = self._latest
            if blob:
                query.reply(self.keys.weights, blob)
            self.queries += 1

    def close(self) -> None:
        """Undeclare every publisher (best effort, on the way out)."""
        undeclare_all(self.weights_pub, self.status_pub, *self.ack_pubs.values())
