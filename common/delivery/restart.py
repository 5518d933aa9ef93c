"""One actor id, one process, one transition stream across restarts.

``RUN_DIR/actor-ID/`` holds an actor's identity on disk:

* ``actor.lock`` -- held (``flock``) by the process running this actor: a second process with the same run
  directory is refused at once, also while the first is stopped (SIGSTOP); the lock goes with the process;
* ``stream.json`` -- the stream record (:class:`StreamRecord`): stream id, next ``seq``, next running index,
  what the learner confirmed durable, and whether a process is (or was, when killed) running it. Written
  atomically at the start, before batch files are deleted as durable, and at the end;
* ``outbox/`` -- every batch not yet confirmed durable (:class:`~khgrl.common.delivery.outbox.Outbox`, written through).

:func:`open_stream` decides how a process starts: it *continues* the stream of the record (same stream id,
``seq`` and running index carry on, the outbox is re-read and re-sent) when the earlier process was killed,
left batches the learner has not confirmed, or ``--resume`` was given; otherwise it starts a fresh stream
(a new random id, ``seq`` 0) and deletes what an earlier stream left.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import secrets
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO

from khgrl.common.delivery.outbox import Outbox

__all__ = ["AlreadyRunning", "lock_actor_dir", "StreamRecord", "StreamStart", "open_stream", "LOCK_FILE",
           "RECORD_FILE", "OUTBOX_DIR"]

log = logging.getLogger("khgrl.actor")

LOCK_FILE = "actor.lock"
RECORD_FILE = "stream.json"
OUTBOX_DIR = "outbox"


class AlreadyRunning(RuntimeError):
    """Another live process runs this actor id (same run directory, or alive on the router)."""


def lock_actor_dir(out_dir: Path) -> IO:
    """Take ``RUN_DIR/actor-ID/actor.lock`` for this process (keep the returned file open while running);
    :class:`AlreadyRunning` naming the holder's pid if another process has it.

    :param out_dir: RUN_DIR/actor-ID (exists).
    """
    path = Path(out_dir) / LOCK_FILE
    fh = open(path, "a+")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.seek(0)
        holder = fh.read().strip() or "?"
        fh.close()
        raise AlreadyRunning(f"another process (pid {holder}) runs this actor with run directory {out_dir.parent} "
                             f"(it holds {path})") from None
    fh.seek(0)
    fh.truncate()
    fh.write(str(os.getpid()))
    fh.flush()
    return fh


@dataclass
class StreamRecord:
    """``stream.json``: where an actor's transition stream stands."""

    stream: str  # the stream id (the transitions' ``stream`` field)
    next_seq: int = 0  # the seq of the next batch
    next_index: int = 0  # the running index of the next transition (its batch's ``first_step``)
    durable: int = -1  # the highest seq the learner confirmed durable
    running: bool = True  # a process runs the stream (still true after that process was killed)

    @classmethod
    def load(cls, out_dir: Path) -> "StreamRecord | None":
        """The record in ``out_dir`` (None: none, or unreadable -- logged).

        :param out_dir: RUN_DIR/actor-ID.
        """
        path = Path(out_dir) / RECORD_FILE
        if not path.is_file():
            return None
        try:
            d = json.loads(path.read_text())
            return cls(stream=str(d["stream"]), next_seq=int(d["next_seq"]), next_index=int(d["next_index"]),
                       durable=int(d["durable"]), running=bool(d["running"]))
        except (ValueError, KeyError, TypeError) as exc:
            log.error("%s is unreadable (%s): starting a new stream", path, exc)
            return None

    def save(self, out_dir: Path) -> None:
        """Write it atomically (a temporary file, then a rename).

        :param out_dir: RUN_DIR/actor-ID.
        """
        path = Path(out_dir) / RECORD_FILE
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(asdict(self)))
        os.replace(tmp, path)


@dataclass
class StreamStart:
    """How this process's stream begins (see :func:`open_stream`)."""

    record: StreamRecord  # running, saved
    outbox: Outbox
    continued: bool  # the stream of an earlier process carries on
    killed: bool  # that process did not end (killed, or crashed)


def open_stream(out_dir: Path, memory: int, actor: str, resume: bool) -> StreamStart:
    """Continue this actor's stream or start a fresh one (the module docstring says when), and mark it running.

    :param out_dir: RUN_DIR/actor-ID.
    :param memory: batches the outbox keeps in memory.
    :param actor: this actor's id.
    :param resume: ``--resume`` was given.
    """
    out_dir = Path(out_dir)
    box_dir = out_dir / OUTBOX_DIR
    rec = StreamRecord.load(out_dir)
    if rec is not None:
        box = Outbox.reopen(memory, box_dir, actor, rec.stream, rec.durable)
        if resume or rec.running or len(box):
            killed = rec.running
            newest = box.newest()
            rec = StreamRecord(stream=rec.stream, next_seq=max(rec.next_seq, -1 if newest is None else newest + 1),
                               next_index=max(rec.next_index, box.end_index), durable=rec.durable)
            rec.save(out_dir)
            log.info("actor %s continues stream %s%s: next seq %d, next transition %d, %d batches (%d transitions) "
                     "not confirmed durable (durable through seq %d)", actor, rec.stream,
                     " of a process that did not end (killed?)" if killed else "", rec.next_seq, rec.next_index,
                     len(box), box.transitions_after(rec.durable), rec.durable)
            return StreamStart(rec, box, continued=True, killed=killed)
    dropped = Outbox.clear(box_dir) if box_dir.is_dir() else 0
    if dropped:
        log.warning("actor %s starts a new stream: deleted %d batch files of an earlier one", actor, dropped)
    rec = StreamRecord(stream=secrets.token_hex(6))
    rec.save(out_dir)
    return StreamStart(rec, Outbox(memory, box_dir), continued=False, killed=False)
