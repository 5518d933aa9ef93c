"""The actor's outbox: every encoded batch of transitions by ``seq`` until the learner says it is durable
(in a learner checkpoint).

Every batch is written to ``RUN_DIR/actor-ID/outbox/<seq>.msgpack`` before it is published (write-through,
atomically: a temporary file, then a rename), so an actor killed at any moment leaves every batch it ever
published on disk, and a restarted actor re-reads them (:meth:`Outbox.reopen`) and re-sends those the learner
may not hold. The newest ``memory`` batches are also kept in memory, so a re-send rarely reads the disk; older
ones are "spilled" (dropped from memory, read back from their file when needed). A batch's file is deleted
once the learner confirms it durable.
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict, deque
from pathlib import Path

__all__ = ["Outbox", "SUFFIX"]

log = logging.getLogger("khgrl.actor")

SUFFIX = ".msgpack"


class Outbox:
    """Encoded batches by seq, with the number of transitions in each.

    :param memory: batches kept in memory as well as on disk (the newest ones).
    :param spill_dir: where every batch is written (one file per batch; created on the first batch).
    """

    def __init__(self, memory: int, spill_dir: Path) -> None:
        self.memory = max(1, int(memory))
        self.spill_dir = Path(spill_dir)
        self.mem: OrderedDict[int, bytes] = OrderedDict()  # the newest batches' payloads
        self.held: deque[int] = deque()  # every seq held (each has its file), oldest first
        self.sizes: dict[int, int] = {}  # seq -> transitions in that batch
        self.spilled_total = 0  # batches dropped from memory (their file is read when they are re-sent)
        self.end_index = 0  # a reopened outbox: the running index after its newest batch (0: none)
        self._dir_made = False

    def _path(self, seq: int) -> Path:
        return self.spill_dir / f"{seq:012d}{SUFFIX}"

    def add(self, seq: int, payload: bytes, n: int) -> None:
        """Keep batch ``seq`` (seqs are added in increasing order): written to its file before this returns.

        :param seq: the batch's sequence number.
        :param payload: the encoded ``transitions`` message.
        :param n: transitions in it.
        """
        if not self._dir_made:
            self.spill_dir.mkdir(parents=True, exist_ok=True)
            self._dir_made = True
        path = self._path(seq)
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(payload)
        os.replace(tmp, path)
        self.held.append(seq)
        self.mem[seq] = payload
        self.sizes[seq] = int(n)
        while len(self.mem) > self.memory:
            self.mem.popitem(last=False)
            self.spilled_total += 1

    def get(self, seq: int) -> bytes:
        """The payload of batch ``seq`` (from memory or disk).

        :param seq: a seq still held.
        """
        if seq in self.mem:
            return self.mem[seq]
        return self._path(seq).read_bytes()

    def drop_through(self, durable: int) -> int:
        """Forget every batch up to and including ``durable`` (and delete its file); returns how many.

        :param durable: the highest seq the learner holds in a checkpoint.
        """
        n = 0
        while self.held and self.held[0] <= durable:
            seq = self.held.popleft()
            self._path(seq).unlink(missing_ok=True)
            self.mem.pop(seq, None)
            self.sizes.pop(seq, None)
            n += 1
        return n

    def seqs_after(self, seq: int) -> list[int]:
        """The seqs held that are above ``seq``, in order.

        :param seq: exclusive lower bound.
        """
        return [s for s in self.held if s > seq]

    def transitions_after(self, seq: int) -> int:
        """Transitions in the batches held above ``seq``.

        :param seq: exclusive lower bound (e.g. the durable seq).
        """
        return sum(n for s, n in self.sizes.items() if s > seq)

    def oldest(self) -> int | None:
        return self.held[0] if self.held else None

    def newest(self) -> int | None:
        return self.held[-1] if self.held else None

    def __len__(self) -> int:
        return len(self.held)

    # ------------------------------------------------------------------ another process's outbox
    @staticmethod
    def clear(spill_dir: Path) -> int:
        """Delete every batch file in ``spill_dir`` (an actor starting afresh); returns how many.

        :param spill_dir: the outbox directory.
        """
        n = 0
        for p in Path(spill_dir).glob("*"):
            if p.is_file() and p.suffix in (SUFFIX, ".tmp"):
                p.unlink(missing_ok=True)
                n += int(p.suffix == SUFFIX)
        return n

    @classmethod
    def reopen(cls, memory: int, spill_dir: Path, actor: str, stream: str, durable: int) -> "Outbox":
        """The outbox an earlier process of this actor left: its batch files above ``durable``, re-read and
        checked (files at or below ``durable`` are deleted; a file that is not this stream's batch is kept
        aside as ``*.bad`` and logged).

        :param memory: batches kept in memory from now on.
        :param spill_dir: the outbox directory.
        :param actor: this actor's id (every batch must be its).
        :param stream: the stream the batches must belong to.
        :param durable: the highest seq the learner confirmed durable.
        """
        from khgrl.common.wire.protocol import ProtocolError, Transitions, decode

        box = cls(memory, spill_dir)
        for tmp in box.spill_dir.glob("*.tmp"):
            tmp.unlink(missing_ok=True)  # never renamed: the batch was never published
        for path in sorted(box.spill_dir.glob(f"*{SUFFIX}")):
            try:
                seq = int(path.stem)
                if seq <= durable:
                    path.unlink(missing_ok=True)
                    continue
                msg = decode(Transitions, path.read_bytes())
                if msg.envelope.seq != seq or msg.actor != actor or (msg.stream or "") != stream:
                    raise ProtocolError(f"batch {msg.envelope.seq} of {msg.actor}/{msg.stream}")
            except (ValueError, OSError, ProtocolError) as exc:
                log.error("outbox file %s is not batch of stream %s: %s (kept aside as .bad)", path, stream, exc)
                path.replace(path.with_suffix(".bad"))
                continue
            box.held.append(seq)
            box.sizes[seq] = msg.n
            box.end_index = max(box.end_index, msg.first_step + msg.n)
        return box
