"""Actor identity and restart without processes: the written-through outbox and its re-reading, the stream
record (when a process continues the stream of the one before), the lock on RUN_DIR/actor-ID, the stream
continuing in seq and running index, the learner refusing an actor id's earlier stream once a later one came,
and the learner's fair inbox (batches of ids it has not admitted cannot starve an admitted actor).
(With real processes: tests/integration/test_actor_restart.py.)"""

from __future__ import annotations

import json

import numpy as np
import pytest
from khgrl.actor.record import CorrectionRecord, trim_partial_line
from khgrl.common.delivery.ingest import PENDING_IDS, FairInbox, StreamTable
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.restart import AlreadyRunning, StreamRecord, lock_actor_dir, open_stream
from khgrl.common.delivery.stream import LEARNER_APPEARED_RESEND_S, TransitionStream
from khgrl.common.delivery.transport import Inbox
from khgrl.common.wire.checks import RejectCounter
from khgrl.common.wire.messages import Ack, Transitions
from khgrl.common.wire.protocol import Keys, decode, encode

from test_actor_parts import collect

RUN = Keys("unit")


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def make_stream(out_dir, start=None, memory: int = 2):
    """A stream as khgrl.actor.main wires it, on the outbox and record in ``out_dir`` (``start``: open_stream's)."""
    start = start or open_stream(out_dir, memory, "a0", resume=False)
    rec, sent, clock = start.record, [], Clock()
    stream = TransitionStream("a0", rec.stream, start.outbox, sent.append, RejectCounter("actor/a0"), clock=clock,
                              next_seq=rec.next_seq, next_index=rec.next_index, durable=rec.durable,
                              journal=lambda pos: StreamRecord(stream=rec.stream, **pos).save(out_dir),
                              task="0123456789abcdef")
    return stream, sent, clock


def ack(stream: TransitionStream, received: int, durable: int, **kw) -> Ack:
    return Ack(actor="a0", received=received, durable=durable, trained=0, version=0, epoch="e1",
               stream=stream.stream, **kw)


# ------------------------------------------------------------------------------------- the actor's side
def test_outbox_writes_every_batch_through_and_is_reopened(tmp_path):
    d = tmp_path / "outbox"
    stream, sent, _ = make_stream(tmp_path, memory=2)
    collect(stream, 44)
    stream.cut()  # seqs 0..5: five of 8, one of 4 (first steps 0, 8, .., 40)
    assert sorted(p.name for p in d.iterdir()) == [f"{s:012d}.msgpack" for s in range(6)]
    assert stream.outbox.spilled_total == 4 and len(stream.outbox.mem) == 2
    (d / "000000000009.tmp").write_bytes(b"half")  # a write the kill interrupted (never published)
    (d / "000000000007.msgpack").write_bytes(encode(decode(Transitions, sent[0]), "a0", 0))  # not batch 7
    box = Outbox.reopen(3, d, "a0", stream.stream, durable=1)
    assert list(box.held) == [2, 3, 4, 5] and box.sizes == {2: 8, 3: 8, 4: 8, 5: 4} and box.end_index == 44
    assert box.get(2) == sent[2] and box.transitions_after(1) == 28
    assert not (d / "000000000000.msgpack").exists() and not (d / "000000000009.tmp").exists()  # durable / torn
    assert (d / "000000000007.bad").exists()  # kept aside, not re-sent
    assert Outbox.reopen(3, d, "a0", "another-stream", durable=1).held == type(box.held)()  # none is its batch


def test_a_killed_actor_s_successor_continues_its_stream(tmp_path):
    stream, sent, _ = make_stream(tmp_path)
    collect(stream, 36)  # seqs 0..3 cut, 4 transitions not cut: lost with the process (never sent)
    assert stream.on_ack(ack(stream, 3, 1))  # the learner has 0..3, 0..1 in a checkpoint
    rec = StreamRecord.load(tmp_path)
    assert (rec.next_seq, rec.next_index, rec.durable, rec.running) == (4, 32, 1, True)  # written before the drop
    # the process is killed here; the next one with the same id continues
    start = open_stream(tmp_path, 2, "a0", resume=False)
    assert start.continued and start.killed and start.record.stream == stream.stream
    again, resent, clock = make_stream(tmp_path, start)
    assert (again.next_seq, again.count, again.start_index, again.durable) == (4, 32, 32, 1)
    assert again.outbox.seqs_after(-1) == [2, 3]
    clock.t += LEARNER_APPEARED_RESEND_S + 0.01
    again.check_resend(learner_alive=False)  # what the earlier process left goes out again shortly
    b = [decode(Transitions, p) for p in resent]
    assert [(m.envelope.seq, m.first_step, m.base_seq) for m in b] == [(2, 16, 2), (3, 24, 2)]
    resent.clear()
    collect(again, 16)
    b = [decode(Transitions, p) for p in resent]
    assert [m.envelope.seq for m in b] == [4, 5] and [m.first_step for m in b] == [32, 40]
    assert all(m.stream == stream.stream and m.base_seq == 2 for m in b)
    s = again.summary()
    assert (s["transitions"], s["first_index"], s["next_index"], s["last_seq"]) == (16, 32, 48, 5)
    assert again.on_ack(ack(again, 5, 5)) and not list((tmp_path / "outbox").iterdir())
    StreamRecord(stream=again.stream, **again.position(), running=False).save(tmp_path)  # a clean end
    fresh = open_stream(tmp_path, 2, "a0", resume=False)  # nothing left to send, no --resume: a new stream
    assert not fresh.continued and fresh.record.stream != stream.stream and fresh.record.next_seq == 0
    assert json.loads((tmp_path / "stream.json").read_text())["stream"] == fresh.record.stream


def test_when_an_actor_continues_its_stream(tmp_path):
    stream, _, _ = make_stream(tmp_path)
    collect(stream, 16)
    StreamRecord(stream=stream.stream, **stream.position(), running=False).save(tmp_path)
    left = open_stream(tmp_path, 2, "a0", resume=False)  # a clean end that left unconfirmed batches
    assert left.continued and not left.killed and len(left.outbox) == 2
    StreamRecord(stream=stream.stream, next_seq=2, next_index=16, durable=1, running=False).save(tmp_path)
    resumed = open_stream(tmp_path, 2, "a0", resume=True)  # everything durable, but --resume
    assert resumed.continued and resumed.record.next_seq == 2 and resumed.record.next_index == 16
    assert not list((tmp_path / "outbox").iterdir())  # durable files deleted on reopening
    (tmp_path / "stream.json").write_text("{not json")
    assert not open_stream(tmp_path, 2, "a0", resume=True).continued  # an unreadable record: a new stream


def test_superseded_ack_stops_the_stream(tmp_path):
    stream, _, _ = make_stream(tmp_path)
    collect(stream, 16)
    assert not stream.on_ack(ack(stream, -1, -1).replace(stream="other", superseded=True))  # not ours
    assert stream.superseded is None
    assert not stream.on_ack(ack(stream, -1, -1, superseded=True))
    assert "another process runs this actor id" in stream.superseded and len(stream.outbox) == 2  # nothing dropped
    assert decode(Ack, encode(ack(stream, -1, -1, superseded=True), "learner", 0)).superseded is True
    assert decode(Ack, encode(ack(stream, 0, 0), "learner", 0)).superseded is None


def test_actor_dir_lock_refuses_a_second_process(tmp_path):
    held = lock_actor_dir(tmp_path)
    with pytest.raises(AlreadyRunning, match="pid [0-9]+"):
        lock_actor_dir(tmp_path)  # (flock: a second open file is refused like another process)
    held.close()
    lock_actor_dir(tmp_path).close()  # released with the file (and with a killed process)


def test_appending_after_a_kill_cuts_a_half_written_row(tmp_path):
    path = tmp_path / "corrections.csv"
    rec = CorrectionRecord(path, "r", "a0")
    rec.write(1, 3, "c", [0.1, 0.2], {})
    rec.close()
    whole = path.read_text()
    path.write_text(whole + "r,a0,1,4,17")  # killed while the buffer was being written
    assert trim_partial_line(path) == len("r,a0,1,4,17") and path.read_text() == whole
    path.write_text(whole + "r,a0,1,4,17")
    again = CorrectionRecord(path, "r", "a0", append=True)
    again.write(2, 0, "c", [0.3, 0.4], {})
    again.close()
    lines = path.read_text().splitlines()
    assert lines[0].startswith("run,actor") and [ln.split(",")[2:4] for ln in lines[1:]] == [["1", "3"], ["2", "0"]]


# ------------------------------------------------------------------------------------- the learner's side
def tbatch(seq: int, first: int, stream: str, actor: str = "a0", base: int = 0) -> Transitions:
    n = 4
    obs = np.zeros((n, 5), np.float32)
    msg = Transitions(actor=actor, first_step=first, obs=obs, next_obs=obs, action=np.zeros((n, 2), np.float32),
                      reward=np.zeros(n, np.float32), terminated=np.zeros(n, np.uint8),
                      truncated=np.zeros(n, np.uint8), intervened=np.zeros(n, np.uint8), clipped=np.zeros(n, np.uint8),
                      base_seq=base, stream=stream, task="0123456789abcdef")
    return decode(Transitions, encode(msg, actor, seq))


def test_learner_never_goes_back_to_an_earlier_stream_of_an_actor_id():
    table = StreamTable()
    assert table.offer(tbatch(0, 0, "s0")).result == "accepted"
    assert table.offer(tbatch(1, 4, "s0")).result == "accepted"
    assert table.offer(tbatch(0, 0, "s1")).result == "accepted"  # a second process with id a0 (or a fresh start)
    for seq in (2, 3):  # the first one again: refused, not interleaved
        res = table.offer(tbatch(seq, 4 * seq, "s0"))
        assert res.result == "superseded" and res.ready == [] and res.stream.stream == "s1"
    assert table.offer(tbatch(1, 4, "s1")).result == "accepted"
    assert table["a0"].superseded == 2 and table["a0"].next_seq == 2 and len(table.codes) == 2
    again = StreamTable.from_state(json.loads(json.dumps(table.state())))  # a resumed learner remembers
    assert again.offer(tbatch(4, 16, "s0")).result == "superseded"
    assert again.offer(tbatch(2, 8, "s1")).result == "accepted"


def put(inbox: Inbox, actor: str, seq: int) -> None:
    inbox.put(("transitions", RUN.transitions(actor), f"{actor}/{seq}".encode(), 0.0))


def test_fair_inbox_fake_ids_cannot_starve_an_admitted_actor():
    inbox = Inbox(maxsize=100_000, overflow="drop_newest")
    admitted = {"a0"}
    fair = FairInbox(inbox, admitted.__contains__, clock=Clock())
    for i in range(3000):  # 3,000 fake ids with a batch each, in front of the real actor's
        put(inbox, f"fake{i}", 0)
    for seq in range(5):
        put(inbox, "a0", seq)
    got = [fair.get()[2] for _ in range(10)]
    assert [g for g in got if g.startswith(b"a0/")] == [f"a0/{s}".encode() for s in range(5)]
    assert got[:4] == [b"fake0/0", b"a0/0", b"fake1/0", b"a0/1"]  # turn about: the others share one turn
    assert fair.dropped == 3000 - PENDING_IDS and len(fair.pending) == PENDING_IDS - 5
    assert fair.qsize() == PENDING_IDS - 5


def test_fair_inbox_admits_new_ids_at_a_bounded_rate_and_keeps_control_in_place():
    clock = Clock()
    inbox = Inbox(maxsize=1000)
    admitted: set[str] = {"a0"}
    fair = FairInbox(inbox, admitted.__contains__, admit_per_s=1.0, clock=clock)
    fair.tokens = 1.0
    put(inbox, "a1", 0)
    put(inbox, "a1", 1)
    put(inbox, "a2", 0)
    put(inbox, "a0", 0)
    inbox.put(("control", RUN.control("learner"), b"stop", 0.0))
    put(inbox, "a1", 2)
    put(inbox, "a0", 1)
    # control after the admitted actors' batches that came before it, not after those of ids not admitted yet
    # (they trickle in at the admission rate: a control message cannot wait for them)
    assert [fair.get()[2] for _ in range(3)] == [b"a1/0", b"a0/0", b"stop"]
    assert fair.get()[2] == b"a0/1" and fair.get() is None  # no token left for a2; a1 is not admitted yet either
    admitted.add("a1")  # the loop took a1's first batch: its stream exists now
    assert fair.get()[2] == b"a1/1" and fair.get()[2] == b"a1/2"  # a1 moves to its own turn at once
    assert fair.get() is None
    clock.t += 1.0
    assert fair.get()[2] == b"a2/0"
    assert fair.get() is None and fair.qsize() == 0 and fair.waiting_new == 0


def test_learner_tells_a_superseded_stream_at_once(tmp_path):
    from khgrl.common.config.settings import TQCSettings
    from khgrl.common.process import StopFlag
    from khgrl.learner.loop import LearnerLoop, open_learner

    class Collect:
        queries = 0

        def __init__(self) -> None:
            self.acks: list[Ack] = []

        def ack(self, msg: Ack) -> None:
            self.acks.append(decode(Ack, encode(msg, "learner", len(self.acks))))

        def weights(self, msg) -> None:
            pass

        status = weights

    tqc = TQCSettings(learning_starts=1000, buffer_size=100, net_arch=(8, 8), batch_size=8)
    trainer, streams = open_learner(tqc, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    pub = Collect()
    loop = LearnerLoop(trainer, streams, pub, learner_id="learner", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag())
    assert [loop.offer(tbatch(0, 0, "s0")), loop.offer(tbatch(0, 0, "s1"))] == ["accepted", "accepted"]
    assert loop.offer(tbatch(1, 4, "s0")) == "superseded" and trainer.total == 8
    (sup,) = pub.acks
    assert sup.stream == "s0" and sup.superseded is True and (sup.received, sup.durable) == (-1, -1)
    loop.step()
    assert [(a.stream, a.superseded, a.received) for a in pub.acks[1:]] == [("s1", None, 0)]
