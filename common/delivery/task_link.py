"""The task descriptor on the wire: announce one (actors, the learner) and fetch one (the learner, the GUI,
monitors, third-party clients). Key: ``khgrl/<run>/task/<role>/<id>``; message: ``task``
(:class:`~khgrl.common.wire.messages.TaskInfo`), put once when announced and answered to every query after that."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

from khgrl.common.wire.checks import ProtocolError, RejectCounter
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import TaskInfo
from khgrl.common.wire.protocol import Keys, decode, encode

__all__ = ["TaskAnnouncer", "fetch_task", "fetch_tasks", "task_answers", "TASK_FILE", "save_task", "load_task_file"]

TASK_FILE = "task.msgpack"  # RUN_DIR/learner/task.msgpack: the run's task as the learner builds from it

log = logging.getLogger("khgrl.task")


class TaskAnnouncer:
    """Announces a descriptor on ``task/<role>/<id>``: one put now, and a queryable answering it later.

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param role: ``actor`` or ``learner``.
    :param ident: this process's id.
    :param task: the descriptor.
    """

    def __init__(self, session: Any, keys: Keys, role: str, ident: str, task: TaskDescriptor) -> None:
        self.key = keys.task(role, ident)
        self.payload = encode(TaskInfo(sender_id=ident, descriptor=task), ident, 0)
        self.queryable = session.declare_queryable(self.key, self._answer)
        session.put(self.key, self.payload)

    def _answer(self, query: Any) -> None:
        try:
            query.reply(self.key, self.payload)
        except Exception as exc:  # noqa: BLE001 - a query that went away
            log.debug("task query not answered: %s", exc)

    def undeclare(self) -> None:
        try:
            self.queryable.undeclare()
        except Exception:  # noqa: BLE001 - closing session
            pass


def task_answers(session: Any, keys: Keys, role: str = "actor", timeout: float = 1.0,
                 rejects: RejectCounter | None = None) -> list[tuple[str, TaskDescriptor]]:
    """Every answer of the processes of ``role`` right now, ``(sender id, descriptor)`` (one id may answer twice:
    two processes, e.g. a forged queryable beside the real one).

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param role: ``actor`` or ``learner``.
    :param timeout: seconds to wait for replies.
    :param rejects: where a malformed reply is counted (default: logged).
    """
    out: list[tuple[str, TaskDescriptor]] = []
    try:
        replies = list(session.get(keys.task(role, "*"), timeout=timeout))
    except Exception as exc:  # noqa: BLE001
        log.warning("task query failed: %s", exc)
        return out
    for r in replies:
        if not r.ok:
            continue
        key = str(r.ok.key_expr)
        try:
            info = decode(TaskInfo, r.ok.payload.to_bytes())
            if info.sender_id != Keys.chunk(key, 4):
                raise ProtocolError(f"sender {info.sender_id!r} answered on {key}")
            out.append((info.sender_id, info.descriptor))
        except ProtocolError as exc:
            (rejects or RejectCounter("task")).reject("task", key, exc)
    return out


def fetch_tasks(session: Any, keys: Keys, role: str = "actor", timeout: float = 1.0,
                rejects: RejectCounter | None = None) -> dict[str, TaskDescriptor]:
    """The descriptors the processes of ``role`` answer right now: {sender id: descriptor}.

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param role: ``actor`` or ``learner``.
    :param timeout: seconds to wait for replies.
    :param rejects: where a malformed reply is counted (default: logged).
    """
    return dict(task_answers(session, keys, role, timeout, rejects))


def fetch_task(session: Any, keys: Keys, role: str = "actor", timeout: float = 30.0,
               stop: Callable[[], bool] | None = None) -> TaskDescriptor | None:
    """The run's task as the first process of ``role`` announces it, waiting up to ``timeout`` s (None: not seen).

    :param session: an open Zenoh session.
    :param keys: the run's key expressions.
    :param role: whose descriptor (``actor`` by default: actors build the task).
    :param timeout: seconds to keep asking.
    :param stop: returns True to give up early (a stop signal).
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not (stop is not None and stop()):
        found = fetch_tasks(session, keys, role, timeout=min(1.0, max(0.1, deadline - time.monotonic())))
        if found:
            return found[sorted(found)[0]]
        time.sleep(0.2)
    return None


def save_task(path: Path, task: TaskDescriptor, sender: str = "launcher") -> None:
    """Write ``task`` to ``path`` as a ``task`` message (our own encoding, checked again when read).

    :param path: the file (usually ``RUN_DIR/learner/task.msgpack``).
    :param task: the descriptor.
    :param sender: who wrote it.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(encode(TaskInfo(sender_id=sender, descriptor=task), sender, 0))


def load_task_file(path: Path) -> TaskDescriptor:
    """The descriptor :func:`save_task` wrote (:class:`ProtocolError` if the file is not one)."""
    return decode(TaskInfo, path.read_bytes()).descriptor
