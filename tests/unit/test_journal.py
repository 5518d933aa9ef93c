"""The learner's journal (learner/journal.py) and what the loop and a resumed learner do with it
(learner/loop.py, learner/resume.py), without processes: records written in fsync'd groups, a torn tail dropped,
segments cut at a full checkpoint and deleted once it is in place, a failed write that stops claiming durability,
and a learner resumed from a full checkpoint, the journal after it and a model checkpoint with every transition
exactly once. (With processes and SIGKILL: tests/integration/test_learner_actor.py.)"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
from pathlib import Path

import numpy as np
import pytest
from khgrl.common.process import StopFlag
from khgrl.common.wire.bounds import bad_rows
from khgrl.common.wire.protocol import Ack, Control
from khgrl.learner import journal as journal_module
from khgrl.learner.checkpoint import find_checkpoint, find_model
from khgrl.learner.journal import Journal, journal_dir, segments
from khgrl.learner.journal_record import ARRAYS
from khgrl.learner.journal_scan import read_records
from khgrl.learner.loop import LearnerLoop, open_learner

from test_learner_parts import SMALL, Collect, batch


class _Stream:
    def __init__(self, actor: str = "a0") -> None:
        self.actor, self.durable = actor, -1


def _same(a, b) -> None:
    assert (a.actor, a.stream, a.envelope.seq, a.first_step, a.base_seq) == \
        (b.actor, b.stream, b.envelope.seq, b.first_step, b.base_seq)
    for name, _, _ in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_records_round_trip_and_one_fsync_per_group(tmp_path, monkeypatch):
    fsyncs = []
    real = os.fsync
    monkeypatch.setattr(journal_module.os, "fsync", lambda fd: (fsyncs.append(fd), real(fd))[1])
    j = Journal(tmp_path / "journal")
    s0, s1 = _Stream("a0"), _Stream("a1")
    sent = [batch(i, 8 * i, 8) for i in range(5)] + [batch(0, 0, 3, actor="a1", stream="t")]
    for msg in sent:
        j.append(msg, s1 if msg.actor == "a1" else s0)
    assert j.waiting == 6 and not segments(j.dir)  # nothing written on the ingest path
    marks, exc = j.sync()
    assert exc is None and {id(s0): (s0, 4), id(s1): (s1, 0)} == marks
    assert j.syncs == 1 and len(fsyncs) == 2  # the segment once (a group), and its new directory entry
    assert j.sync() == ({}, None) and j.synced_rows == 43
    got = list(read_records(j.dir))
    assert len(got) == 6
    for a, b in zip(got, sent):
        _same(a, b)


def test_a_torn_tail_is_dropped_and_the_next_segment_read(tmp_path):
    j = Journal(tmp_path / "journal")
    s = _Stream()
    for i in range(3):
        j.append(batch(i, 8 * i, 8), s)
    j.sync()
    path = segments(j.dir)[0][1]
    size = path.stat().st_size
    with open(path, "r+b") as fh:  # the last record cut short, as a kill during the write leaves it
        fh.truncate(size - 10)
    assert [m.envelope.seq for m in read_records(j.dir)] == [0, 1]
    with open(path, "r+b") as fh:  # a flipped byte: the checksum
        fh.seek(size // 3 + 40)
        byte = fh.read(1)
        fh.seek(-1, 1)
        fh.write(bytes([byte[0] ^ 0xFF]))
    assert [m.envelope.seq for m in read_records(j.dir)] == [0]
    again = Journal(j.dir)  # a resumed learner writes a new segment after it
    assert again.index == 1
    again.append(batch(2, 16, 8), s)
    again.sync()
    assert [m.envelope.seq for m in read_records(j.dir)] == [0, 2]


def test_segments_rotate_are_cut_and_deleted_after_a_snapshot(tmp_path):
    j = Journal(tmp_path / "journal", segment_bytes=1)  # a new segment for every group
    s = _Stream()
    for i in range(3):
        j.append(batch(i, 8 * i, 8), s)
        j.sync()
    assert [i for i, _ in segments(j.dir)] == [0, 1, 2]
    j.append(batch(3, 24, 8), s)
    index, marks, exc = j.cut()  # written first, then the next batches go to a new segment
    assert exc is None and list(marks.values()) == [(s, 3)] and index == 4 and j.rows == 0
    assert [m.envelope.seq for m in read_records(j.dir, index)] == []
    j.append(batch(4, 32, 8), s)
    j.sync()
    removed = j.snapshot_saved(index)
    assert len(removed) == 4 and [i for i, _ in segments(j.dir)] == [4]
    assert [m.envelope.seq for m in read_records(j.dir)] == [4]
    assert Journal(j.dir, fresh=True).index == 0 and not segments(j.dir)


def test_a_failed_write_claims_nothing_until_a_snapshot(tmp_path, monkeypatch):
    j = Journal(tmp_path / "journal")
    s = _Stream()
    j.append(batch(0, 0, 8), s)
    j.sync()

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(journal_module.os, "write", full)
    j.append(batch(1, 8, 8), s)
    marks, exc = j.sync()
    assert marks == {} and exc.errno == errno.ENOSPC and j.error
    monkeypatch.undo()
    j.append(batch(2, 16, 8), s)  # not journaled: a later record after a gap would claim seq 1 durable
    assert j.sync() == ({}, None) and [m.envelope.seq for m in read_records(j.dir)] == [0]
    index, _, _ = j.cut()
    j.snapshot_saved(index)  # the snapshot holds seq 1 and 2
    assert not j.error
    j.append(batch(3, 24, 8), s)
    assert list(j.sync()[0].values()) == [(s, 3)]


def test_the_replays_row_check_without_a_task_refuses_what_is_not_finite():
    arrays = {"obs": np.zeros((3, 2), np.float32), "next_obs": np.zeros((3, 2), np.float32),
              "action": np.zeros((3, 1), np.float32), "reward": np.array([0, np.inf, 0], np.float32)}
    arrays["obs"][2, 1] = np.nan
    assert bad_rows(arrays, None).tolist() == [False, True, True]  # (resume.DEFAULT_ROW_CHECK)


# ------------------------------------------------------------------------------------ loop and resume
def _loop(tmp_path: Path, *, resume: bool = False, model_every: int = 0, snapshot_rows: int | None = None,
          row_check=None, tqc=SMALL):
    learner_dir = tmp_path / "learner"
    trainer, streams = open_learner(tqc, 1, learner_dir, resume=resume, logger_formats=("csv",),
                                    row_check=row_check)
    pub = Collect()
    loop = LearnerLoop(trainer, streams, pub, learner_id="L", learner_dir=learner_dir, checkpoint_every=0,
                       flag=StopFlag(), journal=Journal(journal_dir(learner_dir)), model_checkpoint_every=model_every,
                       snapshot_rows=snapshot_rows)
    return loop, pub


def _provenance(loop: LearnerLoop) -> list[tuple[str, int]]:
    rb = loop.trainer.buffer
    n = rb.buffer_size if rb.full else rb.pos
    actors = {i: c["actor"] for i, c in enumerate(loop.streams.codes)}
    return sorted((actors[int(c)], int(s)) for c, s in zip(rb.provenance_actor[:n], rb.provenance_step[:n]))


def test_the_journal_makes_batches_durable_and_a_killed_learner_resumes_exactly_once(tmp_path):
    loop, pub = _loop(tmp_path, model_every=2, snapshot_rows=80)
    for seq in range(6):  # 48 transitions: the first iterations come due (learning_starts 16)
        loop.offer(batch(seq, 8 * seq, 8))
        loop.offer(batch(seq, 4 * seq, 4, actor="a1", stream="t0"))
        loop.step()
    acks = pub.of(Ack)
    # durable from the journal alone: no full checkpoint was written
    assert loop.durable.checkpoints == 0 and find_checkpoint(tmp_path / "learner") is None
    assert [a.durable for a in acks if a.actor == "a0"][-1] == 5
    assert loop.durable.model_checkpoints >= 1 and find_model(tmp_path / "learner") is not None
    for seq in range(6, 9):  # 84 transitions at seq 6: more than snapshot_rows -> a full checkpoint
        loop.offer(batch(seq, 8 * seq, 8))
        loop.offer(batch(seq, 4 * seq, 4, actor="a1", stream="t0"))
        loop.step()
    assert loop.durable.checkpoints == 1 and [i for i, _ in segments(loop.durable.journal.dir)] == [1]
    for seq in range(9, 12):  # after the snapshot: journal only
        loop.offer(batch(seq, 8 * seq, 8))
        loop.step()
    loop.control(Control(command="checkpoint"))  # an actor's request: the journal synced and the model saved
    loop.step()
    assert loop.durable.checkpoints == 1 and [a.durable for a in pub.of(Ack) if a.actor == "a0"][-1] == 11
    model = json.loads((find_model(tmp_path / "learner") / "state.json").read_text())
    assert model["iterations"] == loop.trainer.iterations
    expected, total = _provenance(loop), loop.trainer.total
    positions = {a: loop.streams[a].next_seq for a in loop.streams}
    version, due = loop.trainer.version, list(loop.trainer.due)
    del loop  # killed: no final checkpoint

    again, pub2 = _loop(tmp_path, resume=True)
    assert _provenance(again) == expected and again.trainer.total == total
    assert {a: again.streams[a].next_seq for a in again.streams} == positions
    assert {a: again.streams[a].durable for a in again.streams} == {a: s - 1 for a, s in positions.items()}
    assert again.trainer.version == version and list(again.trainer.due) == due  # the model checkpoint's
    # the actor re-sends what it had out: duplicates, not stored again; then it goes on
    again.offer(batch(11, 88, 8))
    again.offer(batch(12, 96, 8))
    again.step()
    assert again.trainer.total == total + 8 and again.streams["a0"].duplicates == 1


def test_a_learner_resumed_after_its_final_checkpoint_journals_where_the_next_resume_reads(tmp_path):
    """A clean stop's final checkpoint deletes every segment before its ``journal.next``; the learner resumed from it
    must journal from that segment on, or its batches are confirmed durable and then missing at the next resume (a
    grid run lost 332 confirmed batches this way, 2026-12-06)."""
    loop, _ = _loop(tmp_path)
    for seq in range(4):
        loop.offer(batch(seq, 8 * seq, 8))
        loop.step()
    assert loop.checkpoint() is not None  # the clean stop
    del loop
    again, pub = _loop(tmp_path, resume=True)
    for seq in range(4, 8):
        again.offer(batch(seq, 8 * seq, 8))
        again.step()
    again.control(Control(command="checkpoint"))  # the journal synced: acked durable
    again.step()
    assert [a.durable for a in pub.of(Ack) if a.actor == "a0"][-1] == 7
    expected, total = _provenance(again), again.trainer.total
    del again  # killed: no final checkpoint
    third, _ = _loop(tmp_path, resume=True)
    assert third.trainer.total == total == 64 and _provenance(third) == expected


def test_replay_drops_batches_with_bad_rows_but_keeps_the_stream_going(tmp_path):
    tqc = dataclasses.replace(SMALL, learning_starts=1000)  # (no training on the NaN)
    loop, _ = _loop(tmp_path, tqc=tqc)
    reward = np.ones(8, np.float32)
    reward[3] = np.nan  # (as a learner without the ingest bounds check would have stored it)
    bad = batch(1, 8, 8).replace(reward=reward)
    for msg in (batch(0, 0, 8), bad, batch(2, 16, 8)):
        loop.offer(msg)
        loop.step()
    del loop
    again, _ = _loop(tmp_path, resume=True, tqc=tqc)
    assert again.trainer.total == 16 and again.streams["a0"].next_seq == 3 and again.streams["a0"].index == 24
    assert _provenance(again) == [("a0", i) for i in [*range(8), *range(16, 24)]]
    assert np.isfinite(again.trainer.buffer.rewards[:16]).all()
    seen = []
    del again
    _loop(tmp_path, resume=True, tqc=tqc, row_check=lambda arrays, task: seen.append(len(arrays["reward"])) or
          np.zeros(len(arrays["reward"]), bool))
    assert seen == [8, 8, 8]  # the hook is called for every replayed batch


def test_a_fresh_start_removes_an_earlier_learners_journal_and_checkpoints(tmp_path):
    loop, _ = _loop(tmp_path)
    loop.offer(batch(0, 0, 8))
    loop.step()
    loop.checkpoint()
    loop.offer(batch(1, 8, 8))
    loop.step()
    assert segments(loop.durable.journal.dir) and find_checkpoint(tmp_path / "learner")
    fresh, _ = _loop(tmp_path)
    assert not segments(fresh.durable.journal.dir) and find_checkpoint(tmp_path / "learner") is None
    with pytest.raises(Exception, match="no checkpoint"):
        open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",))


def test_a_write_that_fails_while_a_snapshot_is_saved_keeps_the_journal_off(tmp_path, monkeypatch):
    j = Journal(tmp_path / "journal")
    s = _Stream()
    j.append(batch(0, 0, 8), s)
    index, _, _ = j.cut()  # the snapshot holds seq 0; it is written while ingest goes on
    monkeypatch.setattr(journal_module.os, "write", lambda fd, data: (_ for _ in ()).throw(OSError(errno.EIO, "I/O")))
    j.append(batch(1, 8, 8), s)
    assert j.sync()[1] is not None
    monkeypatch.undo()
    j.snapshot_saved(index)  # seq 1 is neither in that snapshot nor in the journal: still off, nothing claimed
    j.append(batch(2, 16, 8), s)
    assert j.error and j.sync() == ({}, None)
    index, _, _ = j.cut()  # the next snapshot (ingest paused while it is saved) holds seq 1 and 2
    j.snapshot_saved(index)
    assert not j.error


def test_ingest_goes_on_into_the_journal_while_a_full_checkpoint_is_saved(tmp_path, monkeypatch):
    from khgrl.learner import durability as loop_module
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    loop, pub = _loop(tmp_path)
    for seq in range(3):
        loop.offer(batch(seq, 8 * seq, 8))
        loop.step()
    real = loop_module.save_checkpoint

    def save_while_ingesting(*args, **kwargs):
        loop.offer(batch(3, 24, 8))  # arrives while the snapshot is written: stored, journaled, durable
        loop.durable.sync_journal()
        assert not loop.lock._is_owned()  # ingest was not paused for the save
        return real(*args, **kwargs)

    monkeypatch.setattr(loop_module, "save_checkpoint", save_while_ingesting)
    assert loop.checkpoint() is not None
    ckpt = find_checkpoint(tmp_path / "learner")
    state = json.loads((ckpt / "state.json").read_text())
    assert state["total_ingested"] == 24 and state["actors"]["a0"]["next_seq"] == 3
    assert sorted(load_checkpoint_arrays(ckpt)["provenance_step"][:24].tolist()) == list(range(24))
    assert [m.envelope.seq for m in read_records(loop.durable.journal.dir, state["journal"]["next"])] == [3]
    assert [a.durable for a in pub.of(Ack)][-1] == 3 and loop.trainer.total == 32
    again, _ = _loop(tmp_path, resume=True)
    assert _provenance(again) == [("a0", i) for i in range(32)] and again.streams["a0"].next_seq == 4


def test_eval_takes_the_most_trained_model(tmp_path):
    from khgrl.learner.checkpoint import newest_model

    loop, _ = _loop(tmp_path, model_every=1)
    for seq in range(4):
        loop.offer(batch(seq, 8 * seq, 8))
        loop.step()
    learner_dir = tmp_path / "learner"
    assert newest_model(learner_dir) == find_model(learner_dir) and find_checkpoint(learner_dir) is None
    loop.checkpoint()
    assert newest_model(learner_dir) == find_checkpoint(learner_dir)  # as trained as the model checkpoint, or more


def test_a_disk_that_does_not_keep_up_stops_the_journal_not_the_memory(tmp_path, monkeypatch):
    monkeypatch.setattr(journal_module, "MAX_WAITING_BYTES", 1000)  # 2 batches of 8 (448 bytes each)
    j = Journal(tmp_path / "journal")
    s = _Stream()
    for i in range(4):  # nothing synced meanwhile (a stalled fsync)
        j.append(batch(i, 8 * i, 8), s)
    assert j.error.startswith("EIO") and j.waiting == 0 and j.sync() == ({}, None)
    index, _, _ = j.cut()
    j.snapshot_saved(index)
    assert not j.error
