"""A damaged journal (learner/journal_scan.py, learner/journal_loss.py, learner/journal_mark.py), without processes:
a torn tail (bytes never confirmed) is told from damage to what was confirmed -- a bit flip mid-segment, a
truncated segment, a missing one --; a resumed learner refuses damage with one line naming the file, the byte and
the confirmed batches affected, or (accepted) steps over the holes, counts them and leaves the tails to the actors.
(With processes: tests/integration/test_resume_journal.py.)"""

from __future__ import annotations

from pathlib import Path

import pytest
from khgrl.learner.journal import Journal, journal_dir, segments
from khgrl.learner.journal_loss import JournalDamage
from khgrl.learner.journal_mark import MARK_FILE, load_mark, remove_mark
from khgrl.learner.journal_scan import JournalScan
from khgrl.learner.resume import open_learner

from test_learner_parts import SMALL, batch


class _Stream:
    def __init__(self, actor: str = "a0") -> None:
        self.actor, self.durable = actor, -1


def _journal(tmp_path: Path, groups: int = 3, per_group: int = 2) -> tuple[Journal, list[int]]:
    """A learner's journal (no full checkpoint) with ``groups`` fsynced groups of a0's batches; the byte offset of
    each record."""
    j = Journal(journal_dir(tmp_path / "learner"))
    s, seq = _Stream(), 0
    for _ in range(groups):
        for _ in range(per_group):
            j.append(batch(seq, 8 * seq, 8, base=seq), s)  # (base: the actor dropped what was acked durable)
            seq += 1
        j.sync()
    offsets = [rec.offset for rec in JournalScan(j.dir).records()]
    return j, offsets


def _flip(path: Path, at: int) -> None:
    data = bytearray(path.read_bytes())
    data[at] ^= 0x10
    path.write_bytes(bytes(data))


def _seqs(scan: JournalScan) -> list[int]:
    return [rec.msg.envelope.seq for rec in scan.records()]


def _resume(tmp_path: Path, accept: bool = False):
    return open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",),
                        accept_journal_loss=accept)


def test_the_mark_says_what_each_group_confirmed(tmp_path):
    j, offsets = _journal(tmp_path)
    path = segments(j.dir)[0][1]
    mark = load_mark(j.dir)
    assert mark.segments == {0: path.stat().st_size} and mark.durable == {"a0": ("s0", 5)}
    (j.dir / MARK_FILE).write_bytes(b"KJM1" + b"\0" * 20)  # a damaged mark counts as none
    assert load_mark(j.dir) is None


def test_a_torn_tail_beyond_the_confirmed_bytes_is_not_damage(tmp_path):
    j, _ = _journal(tmp_path)
    path = segments(j.dir)[0][1]
    whole = path.read_bytes()
    with open(path, "ab") as fh:  # a group written in part when the learner was killed, never confirmed
        fh.write(whole[:100])
    scan = JournalScan(j.dir)
    assert _seqs(scan) == list(range(6)) and scan.damage == []
    trainer, streams = _resume(tmp_path)
    assert streams["a0"].next_seq == 6 and streams.journal_loss is None and trainer.total == 48


def test_a_bit_flip_mid_segment_is_damage_and_refused_with_one_line(tmp_path):
    j, offsets = _journal(tmp_path)
    path = segments(j.dir)[0][1]
    _flip(path, offsets[2] + 60)  # inside batch 2's body: its checksum fails, batches 3..5 follow it whole
    before = path.read_bytes()
    scan = JournalScan(j.dir)
    assert _seqs(scan) == [0, 1, 3, 4, 5]  # reading goes on at the next whole record
    assert [(d.file, d.offset) for d in scan.damage] == [(path.name, offsets[2])]
    assert "checksum mismatch" in scan.damage[0].problem
    with pytest.raises(JournalDamage) as err:
        _resume(tmp_path)
    line = str(err.value)
    assert "\n" not in line and f"{path.name} at byte {offsets[2]}" in line and "a0 2..2" in line, line
    assert "--accept-journal-loss" in line
    assert path.read_bytes() == before and load_mark(j.dir).durable == {"a0": ("s0", 5)}  # nothing changed
    # accepted: the stream steps over the hole, which is counted lost; everything else is replayed
    trainer, streams = _resume(tmp_path, accept=True)
    st = streams["a0"]
    assert st.next_seq == 6 and st.skipped == 1 and trainer.total == 40 and st.index == 48
    assert streams.journal_loss.hole_batches == 1 and streams.journal_loss.unfilled_tails(streams) == 0


def test_a_truncated_segment_is_damage_and_the_tail_is_left_to_the_actors(tmp_path):
    j, offsets = _journal(tmp_path)
    path = segments(j.dir)[0][1]
    with open(path, "r+b") as fh:  # cut at a record boundary: batches 0..2 stay whole
        fh.truncate(offsets[3])
    scan = JournalScan(j.dir)
    assert _seqs(scan) == [0, 1, 2]
    assert [d.offset for d in scan.damage] == [offsets[3]] and "truncated" in scan.damage[0].problem
    with pytest.raises(JournalDamage, match=r"a0 3\.\.5"):
        _resume(tmp_path)
    trainer, streams = _resume(tmp_path, accept=True)
    st = streams["a0"]
    # the ack's received (2) makes the actor re-send 3.. if it still holds them; until then they count as lost
    assert st.next_seq == 3 and trainer.total == 24 and streams.journal_loss.unfilled_tails(streams) == 3
    st.next_seq = 5  # (as if the actor re-sent 3 and 4)
    assert streams.journal_loss.unfilled_tails(streams) == 1


def test_a_missing_segment_and_a_journal_without_a_mark(tmp_path):
    j, offsets = _journal(tmp_path)
    first = segments(j.dir)[0][1]
    again = Journal(j.dir)  # a resumed learner's segment after it
    again.append(batch(6, 48, 8), _Stream())
    again.sync()
    assert load_mark(j.dir).segments == {0: first.stat().st_size, 1: segments(j.dir)[1][1].stat().st_size}
    first.unlink()
    with pytest.raises(JournalDamage, match="segment-000000.bin at byte 0 .missing"):
        _resume(tmp_path)
    # without a mark (a journal of an older learner): a flip with whole records after it is still damage
    remove_mark(j.dir)
    k, offsets = _journal(tmp_path / "old")
    remove_mark(k.dir)
    _flip(segments(k.dir)[0][1], offsets[1] + 60)
    scan = JournalScan(k.dir)
    assert _seqs(scan) == [0, 2, 3, 4, 5] and len(scan.damage) == 1


def test_the_learners_own_skip_is_not_a_hole(tmp_path):
    """A batch stored after the learner skipped batches its actor no longer held (base_seq) is replayed as it was
    stored: the same skip, no damage; the same base_seq without that skip recorded is a hole."""
    j = Journal(journal_dir(tmp_path / "learner"))
    s = _Stream()
    j.append(batch(0, 0, 8), s)
    s.skipped = 2  # the ingest thread skipped 1 and 2 before storing 3
    j.append(batch(3, 24, 8, base=3), s)
    j.sync()
    trainer, streams = _resume(tmp_path)
    assert streams.journal_loss is None and streams["a0"].next_seq == 4 and streams["a0"].skipped == 2
    k = Journal(journal_dir(tmp_path / "other" / "learner"))
    s = _Stream()
    for seq in (0, 3):  # no skip recorded: batches 1 and 2 were stored, and the journal lost them
        k.append(batch(seq, 8 * seq, 8, base=seq), s)
    k.sync()
    hole = r"batches missing in segment-000000.bin before byte 570; confirmed batches affected: a0 1\.\.2"
    with pytest.raises(JournalDamage, match=hole):
        _resume(tmp_path / "other")


def test_a_flip_beyond_the_confirmed_bytes_is_a_torn_tail(tmp_path):
    """Bytes written after the last confirmed group (a machine stopped before their fsync returned) are never acked:
    a damaged record there ends the segment even if whole records follow it, and nothing is refused."""
    j, _ = _journal(tmp_path, groups=2)
    path = segments(j.dir)[0][1]
    confirmed = path.stat().st_size
    more = Journal(tmp_path / "scratch")  # the bytes of a later group, appended without updating the mark
    s = _Stream()
    for seq in (4, 5):
        more.append(batch(seq, 8 * seq, 8, base=seq), s)
    more.sync()
    with open(path, "ab") as fh:
        fh.write(segments(more.dir)[0][1].read_bytes())
    _flip(path, confirmed + 60)
    scan = JournalScan(j.dir)
    assert _seqs(scan) == [0, 1, 2, 3] and scan.damage == []
    trainer, streams = _resume(tmp_path)
    assert streams.journal_loss is None and streams["a0"].next_seq == 4
