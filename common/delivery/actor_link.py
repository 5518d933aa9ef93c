"""The actor's Zenoh declarations: what it subscribes to (acks, corrections, control, learner liveliness,
weights), what it publishes (transitions, frames, episodes, scale, status, its checkpoint requests on its own
``actor/<id>/request``), its liveliness token, and the queries it makes (who is alive, the current weights).
Acks, corrections and commands wait in Zenoh's ring buffers (:class:`~khgrl.common.delivery.transport.Rings`), learner
liveliness
in an :class:`~khgrl.common.delivery.transport.Inbox`; the control loop takes them out, a bounded number per step."""

from __future__ import annotations

import logging

from khgrl.common.delivery.transport import Inbox, Rings, undeclare_all
from khgrl.common.wire.checks import ProtocolError
from khgrl.common.wire.messages import Ack, Control, Correction, Message
from khgrl.common.wire.protocol import Keys, RejectCounter, encode

__all__ = ["ActorLink", "actor_alive"]

log = logging.getLogger("khgrl.actor")


def actor_alive(session, keys: Keys, actor: str, timeout: float = 2.0) -> str | None:
    """The liveliness key of a live process of actor ``actor`` on the router (None: there is none, or the query
    failed -- logged). Asked before this process declares anything, so any reply is another process.

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param actor: the actor id.
    :param timeout: seconds to wait for replies.
    """
    found = None
    try:
        for r in session.liveliness().get(keys.alive("actor", actor), timeout=timeout):
            if r.ok and found is None:
                found = str(r.ok.key_expr)
    except Exception as exc:  # noqa: BLE001
        log.warning("liveliness query for actor %s failed: %s", actor, exc)
    return found


def _count_oversize(rejects: RejectCounter):
    """Count (and log, rate-limited) a payload the rings skipped for its size, as the decoder would have."""

    def on_oversize(kind: str, key: str, size: int, limit: int) -> None:
        kind = "control" if kind == "human_request" else kind
        rejects.reject(kind, key, ProtocolError(f"{size} bytes exceeds the {kind} limit of {limit}"))

    return on_oversize


class ActorLink:
    """Everything the actor declares on its Zenoh session.

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param actor: this actor's id.
    :param inbox: where the liveliness callback puts ``(kind, key, appeared, arrival)``.
    :param rejects: where payloads over their kind's limit are counted (None: only in ``rings.oversize``).
    """

    def __init__(self, session, keys: Keys, actor: str, inbox: Inbox, rejects: RejectCounter | None = None) -> None:
        import zenoh

        self.session = session
        self.keys = keys
        self.actor = actor
        # acks, corrections and commands wait in Zenoh's ring buffers, polled by the control loop (a flood on them
        # costs the loop nothing); learner liveliness comes through the inbox's callback
        self.rings = Rings(session, on_oversize=None if rejects is None else _count_oversize(rejects))
        for kind, key, capacity, limit in (
                ("ack", keys.ack(actor), 64, Ack.MAX_BYTES), ("correction", keys.correction("*"), 256,
                                                              Correction.MAX_BYTES),
                ("control", keys.control("actor"), 16, Control.MAX_BYTES),
                ("control", keys.control(actor), 16, Control.MAX_BYTES),
                ("control", keys.control("all"), 16, Control.MAX_BYTES),
                ("human_request", keys.human_request("*"), 16, Control.MAX_BYTES)):
            self.rings.add(kind, key, capacity, limit)
        self.subs = [session.liveliness().declare_subscriber(keys.learners_alive, inbox.liveliness_callback("alive"),
                                                             history=True)]
        block, drop = zenoh.CongestionControl.BLOCK, zenoh.CongestionControl.DROP
        self.pubs = {
            "transitions": session.declare_publisher(keys.transitions(actor), congestion_control=block,
                                                     priority=zenoh.Priority.DATA),
            "frame": session.declare_publisher(keys.frame(actor), congestion_control=drop,
                                               priority=zenoh.Priority.DATA),
            "episode": session.declare_publisher(keys.episode(actor), congestion_control=block),
            "scale": session.declare_publisher(keys.scale(actor), congestion_control=block),
            "status": session.declare_publisher(keys.status("actor", actor), congestion_control=drop,
                                                priority=zenoh.Priority.DATA_LOW),
        }
        self.seq = {"frame": 0, "episode": 0, "scale": 0, "status": 0, "request": 0}
        self.token = None

    def weights_subscriber(self):
        """A subscriber to the learner's weights that keeps only the newest sample (RingChannel(1))."""
        import zenoh

        return self.session.declare_subscriber(self.keys.weights, zenoh.handlers.RingChannel(1))

    def announce(self) -> None:
        """Declare this actor's liveliness token."""
        self.token = self.session.liveliness().declare_token(self.keys.alive("actor", self.actor))

    def learners_alive(self, timeout: float = 1.0) -> set[str]:
        """Liveliness keys of the learners alive right now (``alive/learner/<id>/<epoch>``; a liveliness query).

        :param timeout: seconds to wait for replies.
        """
        out: set[str] = set()
        try:
            for r in self.session.liveliness().get(self.keys.learners_alive, timeout=timeout):
                if r.ok:
                    out.add(str(r.ok.key_expr))
        except Exception as exc:  # noqa: BLE001
            log.warning("liveliness query failed: %s", exc)
        return out

    def other_task(self, mine, timeout: float = 1.0) -> str | None:
        """Why a learner alive now cannot train this actor (it was built for another task), or None.

        :param mine: this actor's :class:`~khgrl.common.wire.descriptor.TaskDescriptor`.
        :param timeout: seconds to wait for the learners' answers.
        """
        from khgrl.common.delivery.task_link import fetch_tasks

        for lid, theirs in fetch_tasks(self.session, self.keys, "learner", timeout=timeout).items():
            if theirs.digest != mine.digest:
                return (f"learner {lid} was built for task {theirs.name!r} ({theirs.out_dim} outputs, "
                        f"{theirs.obs_dim} observations, digest {theirs.digest}); this actor runs {mine.name!r} "
                        f"({mine.out_dim} outputs, {mine.obs_dim} observations, digest {mine.digest}): start them "
                        f"with one task")
        return None

    def query_weights(self, timeout: float) -> list[bytes]:
        """The payloads the learner's weights queryable answers (empty on failure).

        :param timeout: seconds to wait for replies.
        """
        try:
            replies = list(self.session.get(self.keys.weights, timeout=timeout))
        except Exception as exc:  # noqa: BLE001
            log.warning("weights query failed: %s", exc)
            return []
        return [r.ok.payload.to_bytes() for r in replies if r.ok]

    def publish(self, msg: Message) -> None:
        """Publish a frame, episode report, scale or status, numbered per kind.

        :param msg: the message (its kind picks the publisher).
        """
        kind = msg.KIND
        self.pubs[kind].put(encode(msg, self.actor, self.seq[kind]))
        self.seq[kind] += 1

    def publish_transitions(self, payload: bytes) -> None:
        """Publish an encoded ``transitions`` batch (new or re-sent).

        :param payload: the encoded message.
        """
        self.pubs["transitions"].put(payload)

    def request_checkpoint(self) -> None:
        """Ask the learner for a checkpoint: a ``control`` ``checkpoint`` on this actor's own ``actor/<id>/request``
        (``control/**`` is the launcher's)."""
        self.session.put(self.keys.request(self.actor),
                         encode(Control(command="checkpoint"), self.actor, self.seq["request"]))
        self.seq["request"] += 1

    def close(self) -> None:
        """Undeclare everything (best effort)."""
        self.rings.undeclare()
        undeclare_all(*self.subs, *self.pubs.values(), *([self.token] if self.token is not None else []))
