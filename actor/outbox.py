"""The actor's outbox: every encoded batch of transitions by ``seq`` until the learner says it is durable
(in a learner checkpoint). The newest batches stay in memory; older ones are spilled to disk."""

from __future__ import annotations

import os
from collections import OrderedDict, deque
from pathlib import Path

__all__ = ["Outbox"]


class Outbox:
    """Encoded batches by seq, with the number of transitions in each.

    :param memory: batches kept in memory; older ones are written to ``spill_dir`` (one file per batch).
    :param spill_dir: where spilled batches go (created on the first spill).
    """

    def __init__(self, memory: int, spill_dir: Path) -> None:
        self.memory = max(1, int(memory))
        self.spill_dir = Path(spill_dir)
        self.mem: OrderedDict[int, bytes] = OrderedDict()
        self.disk: deque[int] = deque()
        self.sizes: dict[int, int] = {}  # seq -> transitions in that batch
        self.spilled_total = 0

    def _path(self, seq: int) -> Path:
        return self.spill_dir / f"{seq:012d}.msgpack"

    def add(self, seq: int, payload: bytes, n: int) -> None:
        """Keep batch ``seq`` (seqs are added in increasing order).

        :param seq: the batch's sequence number.
        :param payload: the encoded ``transitions`` message.
        :param n: transitions in it.
        """
        self.mem[seq] = payload
        self.sizes[seq] = int(n)
        while len(self.mem) > self.memory:
            old, data = self.mem.popitem(last=False)
            self.spill_dir.mkdir(parents=True, exist_ok=True)
            tmp = self._path(old).with_suffix(".tmp")
            tmp.write_bytes(data)
            os.replace(tmp, self._path(old))
            self.disk.append(old)
            self.spilled_total += 1

    def get(self, seq: int) -> bytes:
        """The payload of batch ``seq`` (from memory or disk).

        :param seq: a seq still held.
        """
        if seq in self.mem:
            return self.mem[seq]
        return self._path(seq).read_bytes()

    def drop_through(self, durable: int) -> int:
        """Forget every batch up to and including ``durable``; returns how many were dropped.

        :param durable: the highest seq the learner holds in a checkpoint.
        """
        n = 0
        while self.disk and self.disk[0] <= durable:
            seq = self.disk.popleft()
            self._path(seq).unlink(missing_ok=True)
            self.sizes.pop(seq, None)
            n += 1
        while self.mem and next(iter(self.mem)) <= durable:
            seq, _ = self.mem.popitem(last=False)
            self.sizes.pop(seq, None)
            n += 1
        return n

    def seqs_after(self, seq: int) -> list[int]:
        """The seqs held that are above ``seq``, in order.

        :param seq: exclusive lower bound.
        """
        return [s for s in self.disk if s > seq] + [s for s in self.mem if s > seq]

    def transitions_after(self, seq: int) -> int:
        """Transitions in the batches held above ``seq``.

        :param seq: exclusive lower bound (e.g. the durable seq).
        """
        return sum(n for s, n in self.sizes.items() if s > seq)

    def oldest(self) -> int | None:
        if self.disk:
            return self.disk[0]
        return next(iter(self.mem)) if self.mem else None

    def newest(self) -> int | None:
        return next(reversed(self.mem)) if self.mem else (self.disk[-1] if self.disk else None)

    def __len__(self) -> int:
        return len(self.mem) + len(self.disk)
