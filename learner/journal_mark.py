"""The journal's mark: what the learner confirmed durable from its journal, so that a resumed learner can tell a torn
tail (bytes never confirmed) from damage to what was confirmed (:mod:`khgrl.learner.journal_scan`).

``CHECKPOINT_DIR/journal/confirmed.bin`` holds, after every group the journal wrote and fsynced (before any ack
says those batches are durable): the length in bytes of each segment that is confirmed on disk, and per actor id the
stream and the highest seq confirmed. It is one ``pwrite`` at offset 0 -- a 12-byte header (``b"KJM1"``, the body's
length, its CRC-32) and a JSON body -- without its own fsync: a learner killed at any point leaves either the old or
the new mark (one write call into the page cache), never a torn one; after a power loss it may lag behind the
segments (it was written after their fsync), so it never claims more than they hold. A mark that does not read
(damaged) counts as none: the resumed learner then tells damage from a torn tail by the records alone.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["MARK_FILE", "JournalMark", "load_mark", "save_mark", "remove_mark"]

MARK_FILE = "confirmed.bin"
_MAGIC = b"KJM1"
_HEAD = struct.Struct("<4sII")  # magic, body length, crc32(body)


@dataclass
class JournalMark:
    """What the journal confirmed: ``segments`` {segment index: bytes confirmed}, ``durable`` {actor id: (stream id,
    highest seq confirmed)}."""

    segments: dict[int, int] = field(default_factory=dict)
    durable: dict[str, tuple[str, int]] = field(default_factory=dict)

    def encode(self) -> bytes:
        """The mark file's bytes."""
        body = json.dumps({"segments": {str(i): n for i, n in self.segments.items()},
                           "durable": {a: [s, q] for a, (s, q) in self.durable.items()}}).encode()
        return _HEAD.pack(_MAGIC, len(body), zlib.crc32(body)) + body


def load_mark(directory: str | Path) -> JournalMark | None:
    """The journal's mark (None: there is none, or it does not read).

    :param directory: the journal directory
    """
    try:
        data = (Path(directory) / MARK_FILE).read_bytes()
        magic, size, crc = _HEAD.unpack_from(data, 0)
        body = data[_HEAD.size:_HEAD.size + size]
        if magic != _MAGIC or len(body) != size or zlib.crc32(body) != crc:
            return None
        raw = json.loads(body)
        return JournalMark(segments={int(i): int(n) for i, n in raw["segments"].items()},
                           durable={str(a): (str(s), int(q)) for a, (s, q) in raw["durable"].items()})
    except (OSError, struct.error, ValueError, KeyError, TypeError):
        return None


def save_mark(directory: str | Path, mark: JournalMark) -> None:
    """Write the mark (one ``pwrite`` at offset 0; an OSError is the caller's).

    :param directory: the journal directory
    :param mark: the mark
    """
    fd = os.open(Path(directory) / MARK_FILE, os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        os.pwrite(fd, mark.encode(), 0)
    finally:
        os.close(fd)


def remove_mark(directory: str | Path) -> None:
    """Delete the mark (a fresh journal).

    :param directory: the journal directory
    """
    (Path(directory) / MARK_FILE).unlink(missing_ok=True)
