"""Reading the learner's journal back (:mod:`khgrl.learner.journal` writes it): every whole record in order, and
what is wrong with the rest -- a torn tail or damage.

A record that is not whole (its header, length or checksum wrong, or it does not decode) is

* a **torn tail** when it lies beyond the bytes the journal's mark (:mod:`khgrl.learner.journal_mark`) says were
  confirmed in its segment -- a group that a learner killed (or a machine stopped) while writing never acked -- or,
  for a segment the mark does not know (a journal written before the mark), when nothing whole follows it. It ends
  its segment, logged as a warning; nothing confirmed is lost (the actors still hold those batches).
* **damage** otherwise: it lies inside the confirmed bytes, or (no mark) a whole record follows it. Reading goes on
  at the next whole record (a bit flip mid-segment costs that record only). A segment shorter than its confirmed
  bytes (truncated) and a confirmed segment that is missing are damage too.

What damage cost -- the confirmed batches a resumed learner lacks -- is found by
:func:`khgrl.learner.resume.replay_journal` from the seqs of the records around it and the mark's ``durable``
(:mod:`khgrl.learner.journal_loss`).
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple

from khgrl.common.wire.protocol import Transitions
from khgrl.learner.journal import segments
from khgrl.learner.journal_mark import JournalMark, load_mark
from khgrl.learner.journal_record import HEAD, MAGIC, MAX_BODY, decode_body

__all__ = ["Damage", "Record", "JournalScan", "read_records"]

log = logging.getLogger("khgrl.learner")


@dataclass(frozen=True)
class Damage:
    """Damage found in the journal: the segment file, the byte offset, what is wrong there."""

    file: str
    offset: int
    problem: str

    def __str__(self) -> str:
        return f"{self.file} at byte {self.offset} ({self.problem})"


class Record(NamedTuple):
    """A whole record: the batch, the batches its stream had skipped when the learner stored it (None: not
    recorded, an older learner's record), its segment file and byte offset."""

    msg: Transitions
    skipped: int | None
    file: str
    offset: int


def _problem(data: memoryview, off: int) -> tuple[str, int]:
    """What is wrong with the record at ``off`` ('' if it is whole) and its body's length."""
    if len(data) - off < HEAD.size:
        return f"{len(data) - off} bytes, shorter than a header", 0
    magic, size, crc = HEAD.unpack_from(data, off)
    if magic != MAGIC or size > MAX_BODY:
        return "not a record header", 0
    body = data[off + HEAD.size:off + HEAD.size + size]
    if len(body) < size:
        return f"{len(body)} of {size} bytes", size
    if zlib.crc32(body) != crc:
        return "checksum mismatch", size
    return "", size


def _next_whole(data: memoryview, off: int) -> int | None:
    """The offset of the next whole record at or after ``off`` (None: there is none)."""
    raw = data.obj if isinstance(data.obj, bytes) else bytes(data)
    at = raw.find(MAGIC, off)
    while at >= 0:
        if not _problem(data, at)[0]:
            return at
        at = raw.find(MAGIC, at + 1)
    return None


@dataclass
class JournalScan:
    """One pass over the journal's segments from index ``start`` on (:meth:`records`); afterwards :attr:`damage`
    lists what was damaged (empty: only torn tails, if any).

    :param directory: the journal directory
    :param start: the first segment (a full checkpoint's ``journal.next``)
    """

    directory: Path
    start: int = 0
    mark: JournalMark | None = None
    damage: list[Damage] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.directory = Path(self.directory)
        if self.mark is None:
            self.mark = load_mark(self.directory)

    def records(self) -> Iterator[Record]:
        """Every whole record, in the order written (:class:`Record`)."""
        found = dict(segments(self.directory))
        confirmed = self.mark.segments if self.mark is not None else {}
        for index in sorted(i for i in confirmed if i >= self.start and i not in found):
            self._damaged(Damage(f"segment-{index:06d}.bin", 0, f"missing; {confirmed[index]} bytes were confirmed"))
        for index, path in sorted(found.items()):
            if index >= self.start:
                yield from self._segment(path, confirmed.get(index))

    def _damaged(self, damage: Damage) -> None:
        self.damage.append(damage)
        log.error("journal damaged: %s", damage)

    def _segment(self, path: Path, confirmed: int | None) -> Iterator[Record]:
        data = memoryview(path.read_bytes())
        off = 0
        while off < len(data):
            problem, size = _problem(data, off)
            if not problem:
                try:
                    msg, skipped = decode_body(data[off + HEAD.size:off + HEAD.size + size])
                except (ValueError, KeyError, TypeError) as exc:
                    problem = f"does not decode: {exc}"
                else:
                    yield Record(msg, skipped, path.name, off)
                    off += HEAD.size + size
                    continue
            after = _next_whole(data, off + 1)
            if (confirmed is not None and off >= confirmed) or (confirmed is None and after is None):
                log.warning("journal %s: the record at byte %d is not whole (%s), beyond what was confirmed: a write "
                            "cut short; the %d bytes from there are ignored", path.name, off, problem, len(data) - off)
                return
            self._damaged(Damage(path.name, off, problem + ("" if after is None else
                                                            f"; {after - off} bytes to the next whole record")))
            if after is None:
                break
            off = after
        if confirmed is not None and len(data) < confirmed:
            self._damaged(Damage(path.name, len(data), f"the file ends {confirmed - len(data)} bytes before the "
                                                       f"{confirmed} confirmed: truncated"))


def read_records(directory: str | Path, start: int = 0) -> Iterator[Transitions]:
    """Every whole record of the segments from index ``start`` on, in the order they were written (each a
    :class:`~khgrl.common.wire.protocol.Transitions` whose ``envelope.seq`` is the batch's seq); damage is logged
    (:class:`JournalScan` says what it was).

    :param directory: the journal directory
    :param start: the first segment to read (a snapshot's ``journal.next``)
    """
    for rec in JournalScan(Path(directory), start).records():
        yield rec.msg
