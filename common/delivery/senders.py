"""What arrives, decoded and checked against the key it came on (docs/protocol.md, "checks that hold without access
control"): a process publishes only on its own keys (``khgrl/<run>/<role>/<id>/...``), so a message whose claimed
author is not the id in its key is refused -- a correction from another client, a batch of another actor, a human's
or actor's request in another's name. With the secure router (access control) such a message never arrives; these
checks hold without it. The one place where the processes parse a key expression (the key's owner,
:func:`owner`), with :mod:`~khgrl.common.delivery.ingest` (the fair inbox's per-actor slot),
:mod:`~khgrl.common.delivery.trust` (the learner's epoch in its liveliness key) and
:mod:`~khgrl.common.delivery.task_link` (the announcer's id).
"""

from __future__ import annotations

from khgrl.common.wire.checks import ProtocolError
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import Ack, Control, Correction, Dims, Message, Transitions
from khgrl.common.wire.protocol import Keys, decode

__all__ = ["owner", "SenderError", "HUMAN_COMMANDS", "read_for_actor", "read_for_learner"]

HUMAN_COMMANDS = ("pause", "resume", "estop", "ready")  # what a human-input client may ask the actors (its request)
_ACTOR_KINDS: dict[str, type[Message]] = {"ack": Ack, "correction": Correction, "control": Control,
                                          "human_request": Control}


class SenderError(ProtocolError):
    """A well-formed message refused for who sent it; counted under ``kind`` (its rejects' kind).

    :param message: why
    :param kind: the kind it is counted as
    """

    def __init__(self, message: str, kind: str) -> None:
        super().__init__(message)
        self.kind = kind


def owner(key: str) -> str:
    """The id in a process's own key: ``owner("khgrl/r/actor/a0/transitions") == "a0"``.

    :param key: the key expression a message came on
    """
    return Keys.chunk(key, 3)


def read_for_actor(kind: str, key: str, payload: bytes, dims: Dims) -> Message:
    """An actor's incoming ``ack``, ``correction``, ``control`` or ``human_request``, decoded and checked; raises
    :class:`ProtocolError` (a :class:`SenderError` for a sender refused).

    :param kind: what it arrived as
    :param key: the key it came on
    :param payload: its bytes
    :param dims: the sizes corrections must have
    """
    msg = decode(_ACTOR_KINDS[kind], payload, dims)
    if kind == "correction" and msg.client != owner(key):
        raise SenderError(f"client {msg.client!r} published on {key}", "correction")
    if kind == "human_request" and (msg.command not in HUMAN_COMMANDS or msg.envelope.sender != owner(key)):
        raise SenderError(f"{msg.command!r} from {msg.envelope.sender!r} on {key}: a human client may only pause, "
                          f"resume, press the e-stop or say ready", "control")
    return msg


def read_for_learner(kind: str, key: str, payload: bytes, dims: Dims, task: TaskDescriptor | None) -> Message:
    """A learner's incoming ``transitions``, ``control`` or ``request`` (a ``control`` on ``actor/<id>/request``:
    only ``checkpoint``, only from that actor), decoded and checked; raises :class:`ProtocolError`.

    :param kind: what it arrived as
    :param key: the key it came on
    :param payload: its bytes
    :param dims: the sizes batches must have
    :param task: the run's task (None: not known yet): batches of another task are refused
    """
    if kind == "transitions":
        msg = decode(Transitions, payload, dims)
        if msg.actor != owner(key):
            raise ProtocolError(f"actor {msg.actor!r} published on {key}")
        if task is not None and msg.task is not None and msg.task != task.digest:
            raise ProtocolError(f"actor {msg.actor} runs a task with digest {msg.task}, this learner was built "
                                f"for {task.name!r} (digest {task.digest}): start them with one task")
        return msg
    cmd = decode(Control, payload)
    if kind == "request":
        if cmd.command != "checkpoint":
            raise ProtocolError(f"command {cmd.command!r} on {key}: an actor may only request a checkpoint")
        if cmd.envelope is not None and cmd.envelope.sender != owner(key):
            raise ProtocolError(f"sender {cmd.envelope.sender!r} published on {key}")
    return cmd
