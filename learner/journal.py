"""The learner's journal: every batch the learner stores, appended to fsync'd segment files, so that an actor's
data is durable moments after it arrives rather than at the next full checkpoint.

Layout: ``CHECKPOINT_DIR/journal/segment-000123.bin``. A segment is a sequence of records, one per batch stored in
the replay buffer, in the order it was stored (the record's format: :mod:`khgrl.learner.journal_record`). A record
whose header, length or checksum is wrong is either the torn tail of a learner killed while writing (bytes never
confirmed: the rest of its segment is ignored) or damage to what was confirmed -- :mod:`khgrl.learner.journal_scan`
tells them apart with the journal's mark (:mod:`khgrl.learner.journal_mark`), which every group written updates
before its batches are acked durable; a resumed learner refuses damage (:mod:`khgrl.learner.resume`).

Writing (group commit): the ingest thread :meth:`Journal.append`\\ s each stored batch to a list in memory (no I/O
on the ingest path); :meth:`Journal.sync` -- the learner's *journal thread* calls it as soon as something waits,
and the training thread before a model checkpoint or a full snapshot -- writes everything waiting in one go, fsyncs
it and closes the file, and returns the highest seq per actor stream now on disk: those are durable (``durable`` in
the acks). Everything that arrived while one fsync ran goes into the next one. The file is open only while a group
is written. A failed write or fsync (disk full, read-only, I/O error) stops the journal: nothing more is journaled
and no ack claims more (the actors keep those batches) until a full snapshot -- which holds everything -- has been
saved; the learner retries that snapshot with backoff (:class:`~khgrl.learner.disk_faults.SaveFaults`).

Snapshots: before a full snapshot (:func:`~khgrl.learner.checkpoint.save_checkpoint`, ingest paused) the learner
:meth:`Journal.cut`\\ s the journal: what waits is written, and later batches go into a new segment whose index the
snapshot records (``journal.next`` in its ``state.json``); once the snapshot is in place the segments before it are
deleted (:meth:`Journal.snapshot_saved`). A resumed learner loads the snapshot and replays the records of the
segments from that index on (:func:`khgrl.learner.journal_scan.read_records`).

The record's format is :mod:`khgrl.learner.journal_record` (the writer here and the reader,
:mod:`khgrl.learner.journal_scan`, both take it from there); damage and what it cost: :mod:`khgrl.learner.journal_loss`.
"""

from __future__ import annotations

import logging
import os
import re
import threading
from pathlib import Path
from typing import Any

from khgrl.common.wire.protocol import Transitions
from khgrl.learner.journal_mark import JournalMark, load_mark, remove_mark, save_mark
from khgrl.learner.journal_record import array_bytes, encode_record

__all__ = ["Journal", "JOURNAL_DIR", "SEGMENT_BYTES", "journal_dir", "segments"]

log = logging.getLogger("khgrl.learner")

JOURNAL_DIR = "journal"
SEGMENT_BYTES = 64 * 2**20  # a new segment once the current one holds this much
MAX_WAITING_BYTES = 256 * 2**20  # batches waiting for a disk that does not keep up: beyond this the journal stops
_NAME = re.compile(r"^segment-(\d{6,})\.bin$")

def journal_dir(ckpt_dir: str | Path) -> Path:
    """The journal directory of a learner's checkpoint directory.

    :param ckpt_dir: ``RUN_DIR/learner`` or the learner's ``--checkpoint-dir``
    """
    return Path(ckpt_dir) / JOURNAL_DIR


def _segment(directory: Path, index: int) -> Path:
    return directory / f"segment-{index:06d}.bin"


def segments(directory: str | Path) -> list[tuple[int, Path]]:
    """The segment files of a journal directory, oldest first, with their indices.

    :param directory: the journal directory
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in directory.iterdir() if (m := _NAME.match(p.name))]
    return sorted(found)


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError:  # a filesystem that cannot fsync a directory
        pass
    finally:
        os.close(fd)


class Journal:
    """The append-only journal of one learner incarnation (see the module's docstring).

    :param directory: the journal directory (created)
    :param fresh: delete the segments there (a learner started anew); else a new segment follows the last one
    :param segment_bytes: start a new segment once the current one holds this much
    """

    def __init__(self, directory: str | Path, *, fresh: bool = False, segment_bytes: int = SEGMENT_BYTES) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        if fresh:
            for _, path in segments(self.dir):
                path.unlink()
            remove_mark(self.dir)
        self.mark = (None if fresh else load_mark(self.dir)) or JournalMark()  # (carried on by a resumed learner)
        found = segments(self.dir)
        self.index = found[-1][0] + 1 if found else 0  # the segment written to
        self.segment_bytes = int(segment_bytes)
        self.size = 0  # bytes in the current segment
        self.rows = 0  # transitions journaled since the last cut
        self.synced_rows = 0  # transitions on disk since the last snapshot saved
        self.error = ""  # set when a write failed: nothing more is journaled until a snapshot
        self.failures = 0  # writes that failed (this process)
        self._cut_failures = 0  # ... when the last cut was made
        self._cut_synced = 0  # synced_rows then
        self.records = 0  # records written (this process)
        self.syncs = 0  # groups written and fsynced (this process)
        self.wake = threading.Event()  # something waits to be written
        self._pending: list[tuple[Any, Transitions, int]] = []  # (stream, batch, the stream's skipped then)
        self._waiting_bytes = 0
        self._mu = threading.Lock()  # _pending, rows, error
        self._io = threading.Lock()  # the files (one group written at a time)

    def append(self, msg: Transitions, stream: Any) -> None:
        """A batch was stored in the replay buffer (ingest thread): journal it with the next group.

        :param msg: the batch (its ``envelope.seq``)
        :param stream: its actor's :class:`~khgrl.common.delivery.ingest.ActorStream` (``durable`` is raised there
            once the record is on disk)
        """
        size = array_bytes(msg)
        with self._mu:
            if self.error:
                return
            if self._waiting_bytes + size > MAX_WAITING_BYTES:  # (a stalled disk must not cost the learner memory)
                self.error = f"EIO {self._waiting_bytes >> 20} MiB wait for a journal disk that does not keep up"
                self.failures += 1
                self._pending, self._waiting_bytes = [], 0
                log.warning("journal: %s; off until the next full checkpoint", self.error)
                return
            self._pending.append((stream, msg, int(getattr(stream, "skipped", 0))))
            self._waiting_bytes += size
            self.rows += msg.n
        self.wake.set()

    @property
    def waiting(self) -> int:
        """Batches appended but not written yet."""
        return len(self._pending)

    def sync(self) -> tuple[dict[int, tuple[Any, int]], OSError | None]:
        """Write and fsync everything appended so far. Returns ``({id(stream): (stream, highest seq)}, None)`` for
        what is now on disk, or ``({}, the error)`` if the write failed (the journal then stops, see the module)."""
        with self._io:
            with self._mu:
                items, self._pending, self._waiting_bytes = self._pending, [], 0
                if self.error:
                    return {}, None
            if not items:
                return {}, None
            try:
                self._write(items)
            except OSError as exc:
                with self._mu:
                    self.error = str(exc) or type(exc).__name__
                    self.failures += 1
                    self._pending, self._waiting_bytes = [], 0
                return {}, exc
        marks: dict[int, tuple[Any, int]] = {}
        for stream, msg, _ in items:
            marks[id(stream)] = (stream, msg.envelope.seq)
        return marks, None

    def _write(self, items: list[tuple[Any, Transitions, int]]) -> None:
        if self.size >= self.segment_bytes:
            self.index, self.size = self.index + 1, 0
        data = b"".join(encode_record(msg, msg.envelope.seq, skipped) for _, msg, skipped in items)
        path = _segment(self.dir, self.index)
        new = not path.exists()
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        if new:
            _fsync_dir(self.dir)
        self.size += len(data)
        self.mark.segments[self.index] = self.size  # confirmed: before any ack says so (the journal's mark)
        for _, msg, _ in items:
            self.mark.durable[msg.actor] = (msg.stream or "", int(msg.envelope.seq))
        save_mark(self.dir, self.mark)
        self.synced_rows += sum(msg.n for _, msg, _ in items)
        self.records += len(items)
        self.syncs += 1

    def cut(self) -> tuple[int, dict[int, tuple[Any, int]], OSError | None]:
        """Before a full snapshot (ingest paused): write what waits, then start a new segment. Returns its index
        (the snapshot's ``journal.next``) and what :meth:`sync` returned."""
        marks, exc = self.sync()
        with self._io:
            if self.size or _segment(self.dir, self.index).exists():
                self.index, self.size = self.index + 1, 0
            try:  # the new segment on disk now: once the snapshot deletes the old ones, it is what a resumed
                self._create_segment()  # learner numbers on from (else it would start at 0, before journal.next)
            except OSError as err:  # (as a failed write: off, claiming nothing, until a snapshot holds it all)
                with self._mu:
                    self.error, self.failures = str(err) or type(err).__name__, self.failures + 1
                exc = exc or err
            self.rows = 0
            self._cut_failures, self._cut_synced = self.failures, self.synced_rows
            return self.index, marks, exc

    def _create_segment(self) -> None:
        """Create the current segment, empty, with its directory entry fsynced."""
        path = _segment(self.dir, self.index)
        if not path.exists():
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT, 0o644))
            _fsync_dir(self.dir)

    def snapshot_saved(self, index: int) -> list[Path]:
        """A full snapshot holding everything before segment ``index`` is in place: delete those segments, and
        journal again if a write had failed before the cut (one that failed since -- while the snapshot was
        written -- left a gap that only the next snapshot covers). Returns the deleted files (one that cannot be
        deleted is logged).

        :param index: what :meth:`cut` returned
        """
        removed = []
        with self._io:
            for i, path in segments(self.dir):
                if i < index:
                    try:
                        path.unlink()
                        removed.append(path)
                    except OSError as exc:
                        log.warning("cannot delete the old journal segment %s (%s)", path, exc)
            self.mark.segments = {i: n for i, n in self.mark.segments.items() if i >= index}
            self._save_mark()
            self.synced_rows = max(0, self.synced_rows - self._cut_synced)
            self._cut_synced = 0
            with self._mu:
                if self.error and self.failures == self._cut_failures:
                    log.warning("journal: on again (the snapshot holds what it missed since: %s)", self.error)
                    self.error = ""
        return removed

    def restart_mark(self, durable: dict[str, tuple[str, int]]) -> None:
        """Say confirmed what a learner resumed past a loss the operator accepted holds (the confirmed batches it
        lacks are counted lost once, not again at the next resume).

        :param durable: {actor id: (stream id, highest seq held)}
        """
        with self._io:
            self.mark.durable = dict(durable)
            self._save_mark()

    def _save_mark(self) -> None:
        try:
            save_mark(self.dir, self.mark)
        except OSError as exc:  # (it then says less than the segments hold: never a false alarm, see journal_mark)
            log.warning("journal: its mark not written (%s)", exc)

    def info(self) -> dict[str, Any]:
        """Counters for the log."""
        return {"segment": self.index, "records": self.records, "syncs": self.syncs, "rows_since_snapshot": self.rows,
                "error": self.error}
