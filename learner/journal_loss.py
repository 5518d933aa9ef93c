"""What a damaged journal cost a resumed learner: the confirmed batches it lacks, per actor stream, and the decision
to refuse or (``--accept-journal-loss``) to go on without them.

Two kinds of gap (:class:`Gap`):

* a **hole**: the journal holds batches of a stream after ones it lost (a damaged record, a truncated segment
  followed by a later one). The stream steps over it: those batches are lost (no actor holds them any more -- they
  were confirmed, so their actor dropped them -- and the stream has taken later ones); counted.
* a **tail**: the journal's mark says batches were confirmed up to a seq that the replay did not reach (the end of
  the journal damaged or cut off). The resumed learner's ack says ``received`` at the gap's start, so the actor
  re-sends those batches if it still holds them (acks it never got); what it no longer holds it skips
  (``base_seq``), and those batches are counted lost then (:attr:`StreamTable.skipped
  <khgrl.common.delivery.ingest.StreamTable.skipped>`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from khgrl.common.delivery.ingest import StreamTable
from khgrl.learner.checkpoint import CheckpointError
from khgrl.learner.journal_scan import Damage, JournalScan, Record

__all__ = ["ACCEPT_FLAG", "Gap", "JournalLoss", "JournalDamage", "check_loss"]

log = logging.getLogger("khgrl.learner")

ACCEPT_FLAG = "--accept-journal-loss"


class JournalDamage(CheckpointError):
    """The journal lost confirmed batches and the operator did not accept the loss (one line)."""


@dataclass(frozen=True)
class Gap:
    """Confirmed batches ``first..last`` of an actor's stream that the journal does not hold (``first`` None: not
    known, the stream's records are all gone); ``kind`` 'hole' or 'tail' (the module's docstring); ``where``: the
    record after the hole, or the journal's end."""

    actor: str
    stream: str
    first: int | None
    last: int
    kind: str
    where: str = ""
    transitions: int | None = None  # (a hole: from the running indices around it)

    def __str__(self) -> str:
        span = f"{self.first}..{self.last}" if self.first is not None else f"up to {self.last} (stream {self.stream})"
        return f"{self.actor} {span}"

    @property
    def batches(self) -> int | None:
        """How many batches (None: not known)."""
        return None if self.first is None else self.last - self.first + 1


@dataclass
class JournalLoss:
    """The damage a journal scan found and the gaps a replay stepped over (true when there is either)."""

    damage: list[Damage] = field(default_factory=list)
    gaps: list[Gap] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.damage or self.gaps)

    def step_over_gap(self, streams: StreamTable, rec: Record) -> None:
        """Before a replayed batch is offered: if batches of its stream are missing in front of it, note the hole and
        move the stream past it. Missing are the batches between the stream's next seq and the record's -- unless
        the learner had skipped them itself when it stored the record (its actor no longer held them: the record's
        ``skipped`` is higher than the stream's), then only those before the batch's ``base_seq``.

        :param streams: the stream table being replayed into
        :param rec: the replayed record
        """
        msg = rec.msg
        st = streams.streams.get(msg.actor)
        if st is None or (msg.stream and st.stream and msg.stream != st.stream):
            return  # (a stream's first batch: it starts where the actor said)
        own_skip = rec.skipped is None or rec.skipped > st.skipped
        expected, seq = max(st.next_seq, msg.base_seq or 0) if own_skip else st.next_seq, msg.envelope.seq
        if seq <= expected:
            return
        gap = Gap(msg.actor, st.stream, expected, seq - 1, "hole", f"{rec.file} before byte {rec.offset}",
                  msg.first_step - st.index)
        self.gaps.append(gap)
        log.error("journal: confirmed batches %s are missing (the journal holds batch %d after them, %s)", gap, seq,
                  gap.where)
        st.next_seq, st.index = seq, msg.first_step

    def finish(self, scan: JournalScan, streams: StreamTable) -> None:
        """After the replay: the scan's damage, and the tails -- batches the journal's mark says were confirmed
        beyond where the replay left each stream.

        :param scan: the scan the replay read
        :param streams: the stream table after the replay
        """
        self.damage = list(scan.damage)
        for g in (g for g in self.gaps if g.kind == "hole"):  # (counted as the stream's skips from now on)
            streams.streams[g.actor].skipped += g.batches
        for actor, (stream, seq) in sorted((scan.mark.durable if scan.mark is not None else {}).items()):
            st = streams.streams.get(actor)
            if st is not None and st.stream == stream and st.next_seq > seq:
                continue
            first = st.next_seq if st is not None and st.stream == stream else None
            gap = Gap(actor, stream, first, seq, "tail", "the journal's end")
            self.gaps.append(gap)
            log.error("journal: confirmed batches %s are missing at the journal's end", gap)

    @property
    def hole_batches(self) -> int:
        """Batches lost in holes (the tails are counted when their actors skip them)."""
        return sum(g.batches or 0 for g in self.gaps if g.kind == "hole")

    def unfilled_tails(self, streams: StreamTable) -> int:
        """Batches of the tails that no actor has re-sent (nor skipped, which :attr:`StreamTable.skipped` counts)
        so far; a tail whose first batch is not known counts as the stream's batches up to its last (at most).

        :param streams: the stream table now
        """
        n = 0
        for g in (g for g in self.gaps if g.kind == "tail"):
            st = streams.streams.get(g.actor)
            if g.first is None:
                n += g.last + 1 if st is None or st.stream != g.stream else max(0, g.last - st.next_seq + 1)
            elif st is not None and st.stream == g.stream:
                n += max(0, g.last - st.next_seq + 1)
        return n

    def line(self) -> str:
        """One line: the first damage (file, byte), how much more, and the confirmed batches affected."""
        where = str(self.damage[0]) if self.damage else f"batches missing in {self.gaps[0].where}"
        more = f" (and {len(self.damage) - 1} more)" if len(self.damage) > 1 else ""
        gaps = ", ".join(str(g) for g in self.gaps) or "none found from the seqs (the damaged records' batches)"
        return f"the journal is damaged: {where}{more}; confirmed batches affected: {gaps}"

    def summary(self) -> dict:
        """For the learner's summary."""
        return {"damage": [str(d) for d in self.damage], "gaps": [str(g) for g in self.gaps],
                "hole_batches": self.hole_batches}


def check_loss(loss: JournalLoss, accept: bool) -> None:
    """Refuse a journal that lost confirmed batches (:class:`JournalDamage`, one line) unless the operator accepted
    the loss; then say so (logged as an error).

    :param loss: what the replay found
    :param accept: ``--accept-journal-loss``
    """
    if not loss:
        return
    if not accept:
        raise JournalDamage(f"--resume refused: {loss.line()}. Nothing was changed; to resume without those "
                            f"batches pass {ACCEPT_FLAG} (actors re-send those they still hold, the rest is counted "
                            f"lost and the learner exits with 3)")
    log.error("%s; resuming without them (%s): actors re-send the tail batches they still hold, %d batches of holes "
              "are lost", loss.line(), ACCEPT_FLAG, loss.hole_batches)
