"""The actor's Zenoh declarations: what it subscribes to (acks, corrections, control, learner liveliness,
weights), what it publishes (transitions, frames, episodes, scale, status, its checkpoint requests on its own
``actor/<id>/request``), its liveliness token, and the queries it makes (who is alive, the current weights).
Acks, corrections and commands wait in Zenoh's ring buffers (:class:`~khgrl.common.delivery.transport.Rings`), learner
liveliness
in an :class:`~khgrl.common.delivery.transport.Inbox`; the control loop takes them out, a bounded number per step."""

from __future__ import annotations

import logging

from khgrl.common.delivery.declare import alive_now, alive_subscriber, publisher, put, query, ring_subscriber, token
from khgrl.common.delivery.transport import Inbox, Rings, undeclare_all
from khgrl.common.wire.checks import ProtocolError
from khgrl.common.wire.messages import Ack, Control, Correction, Message
from khgrl.common.wire.protocol import Keys, RejectCounter, encode

__all__ = ["ActorLink", "actor_alive", "NewestPayload"]

log = logging.getLogger("khgrl.actor")


def actor_alive(session, keys: Keys, actor: str, timeout: float = 2.0) -> str | None:
    """The liveliness key of a live process of actor ``actor`` on the router (None: there is none, or the query
    failed -- logged). Asked before this process declares anything, so any reply is another process.

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param actor: the actor id.
    :param timeout: seconds to wait for replies.
    """
    try:
        found = alive_now(session, keys.alive("actor", actor), timeout)
    except Exception as exc:  # noqa: BLE001
        log.warning("liveliness query for actor %s failed: %s", actor, exc)
        return None
    return found[0] if found else None


def _count_oversize(rejects: RejectCounter):
    """Count (and log, rate-limited) a payload the rings skipped for its size, as the decoder would have."""

    def on_oversize(kind: str, key: str, size: int, limit: int) -> None:
        kind = "control" if kind == "human_request" else kind
        rejects.reject(kind, key, ProtocolError(f"{size} bytes exceeds the {kind} limit of {limit}"))

    return on_oversize


class NewestPayload:
    """A subscriber that keeps only the newest sample (Zenoh's RingChannel(1)), read by a background thread.

    :param subscriber: the ring subscriber
    """

    def __init__(self, subscriber) -> None:
        self.sub = subscriber

    def recv(self):
        """The next payload (Zenoh's ZBytes: its receiver checks the length before copying it), waiting for it;
        raises once the subscriber is undeclared."""
        return self.sub.handler.recv().payload

    def undeclare(self) -> None:
        self.sub.undeclare()


class ActorLink:
    """Everything the actor declares on its Zenoh session.

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param actor: this actor's id.
    :param inbox: where the liveliness callback puts ``(kind, key, appeared, arrival)``.
    :param rejects: where payloads over their kind's limit are counted (None: only in ``rings.oversize``).
    """

    def __init__(self, session, keys: Keys, actor: str, inbox: Inbox, rejects: RejectCounter | None = None) -> None:
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
        self.subs = [alive_subscriber(session, keys.learners_alive, inbox.liveliness_callback("alive"), history=True)]
        self.pubs = {
            "transitions": publisher(session, keys.transitions(actor), congestion="block", priority="data"),
            "frame": publisher(session, keys.frame(actor), congestion="drop", priority="data"),
            "episode": publisher(session, keys.episode(actor), congestion="block"),
            "scale": publisher(session, keys.scale(actor), congestion="block"),
            "status": publisher(session, keys.status("actor", actor), congestion="drop", priority="data_low"),
        }
        self.seq = {"frame": 0, "episode": 0, "scale": 0, "status": 0, "request": 0}
        self.token = None

    def weights_subscriber(self) -> NewestPayload:
        """A subscriber to the learner's weights that keeps only the newest sample (RingChannel(1))."""
        return NewestPayload(ring_subscriber(self.session, self.keys.weights, 1))

    def announce(self) -> None:
        """Declare this actor's liveliness token."""
        self.token = token(self.session, self.keys.alive("actor", self.actor))

    def learners_alive(self, timeout: float = 1.0) -> set[str]:
        """Liveliness keys of the learners alive right now (``alive/learner/<id>/<epoch>``; a liveliness query).

        :param timeout: seconds to wait for replies.
        """
        try:
            return set(alive_now(self.session, self.keys.learners_alive, timeout))
        except Exception as exc:  # noqa: BLE001
            log.warning("liveliness query failed: %s", exc)
            return set()

    def other_tasks(self, mine, timeout: float = 1.0) -> dict[str, str]:
        """The learners answering now that cannot train this actor: {learner id: why} for each id that answers only
        tasks other than ``mine`` (an id that also answers ``mine`` is this actor's learner).

        :param mine: this actor's :class:`~khgrl.common.wire.descriptor.TaskDescriptor`.
        :param timeout: seconds to wait for the learners' answers.
        """
        from khgrl.common.delivery.task_link import task_answers

        answers = task_answers(self.session, self.keys, "learner", timeout=timeout)
        ours = {lid for lid, theirs in answers if theirs.digest == mine.digest}
        return {lid: (f"learner {lid} was built for task {theirs.name!r} ({theirs.out_dim} outputs, "
                      f"{theirs.obs_dim} observations, digest {theirs.digest}); this actor runs {mine.name!r} "
                      f"({mine.out_dim} outputs, {mine.obs_dim} observations, digest {mine.digest}): start them "
                      f"with one task")
                for lid, theirs in answers if lid not in ours}

    def query_weights(self, timeout: float) -> list[bytes]:
        """The payloads the learner's weights queryable answers (empty on failure).

        :param timeout: seconds to wait for replies.
        """
        try:
            return [payload for _, payload in query(self.session, self.keys.weights, timeout)]
        except Exception as exc:  # noqa: BLE001
            log.warning("weights query failed: %s", exc)
            return []

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
        put(self.session, self.keys.request(self.actor),
            encode(Control(command="checkpoint"), self.actor, self.seq["request"]))
        self.seq["request"] += 1

    def close(self) -> None:
        """Undeclare everything (best effort)."""
        self.rings.undeclare()
        undeclare_all(*self.subs, *self.pubs.values(), *([self.token] if self.token is not None else []))
