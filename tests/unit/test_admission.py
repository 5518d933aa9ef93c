"""The learner's per-sender budget (:mod:`khgrl.common.delivery.admission`): checked before a batch is copied out of
Zenoh or decoded; a flooding sender stores nothing while it floods; an honest one never runs dry."""

from __future__ import annotations

from types import SimpleNamespace

from khgrl.common.delivery import admission as adm
from khgrl.common.delivery.admission import Admission
from khgrl.common.delivery.transport import Inbox
from khgrl.common.wire.protocol import encode

from test_learner_parts import RUN, batch, make_loop


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _payload(seq: int, actor: str = "a0") -> bytes:
    m = batch(seq, 8 * seq, 8, actor=actor, stream=f"{actor}s")
    return encode(m.replace(envelope=None), actor, seq)


def test_a_sender_gets_its_burst_then_its_rate_and_a_refusal_penalizes_a_member():
    clock = Clock()
    refused: list = []
    members: set = set()
    a = Admission(members.__contains__, lambda s, n: refused.append(s), clock=clock)
    assert all(a.admit("x", 100) for _ in range(adm.GUEST_BURST))
    assert not a.admit("x", 100) and refused == ["x"]
    assert not a.penalized("x")  # (a guest is not: what gets through is checked as usual)
    assert a.admit("y", 100) and not a.penalized("y")  # (each sender its own bucket)
    clock.t += 1.0
    assert sum(a.admit("x", 100) for _ in range(50)) == int(adm.GUEST_RATE)
    members.add("x")
    assert a.penalized("x")  # (a member stores nothing for PENALTY_S after a refusal)
    clock.t += adm.PENALTY_S + 0.1
    assert not a.penalized("x")


def test_refunds_keep_an_honest_member_within_its_budget_at_any_rate():
    clock = Clock()
    a = Admission(lambda s: True, clock=clock)
    for _ in range(10 * adm.MEMBER_BURST):  # far more than its burst, no time passing: each accepted in order
        assert a.admit("a0", 4000)
        a.refund("a0", 4000)
    assert a.refused == 0 and not a.penalized("a0")


def test_the_byte_budget_refuses_large_batches_and_one_batch_larger_than_the_burst_passes_when_full():
    clock = Clock()
    a = Admission(lambda s: True, clock=clock)
    big = adm.MEMBER_BURST_BYTES + 1
    assert a.admit("a0", big)  # (a full bucket takes one batch of any size)
    assert not a.admit("a0", 2**20)
    clock.t += 1.0  # refills MEMBER_BYTES_PER_S
    assert a.admit("a0", adm.MEMBER_BYTES_PER_S // 2)


def test_a_guest_that_becomes_a_member_keeps_what_it_spent():
    clock = Clock()
    members: set = set()
    a = Admission(members.__contains__, clock=clock)
    for _ in range(adm.GUEST_BURST):
        assert a.admit("a1", 10)
    members.add("a1")
    n = sum(a.admit("a1", 10) for _ in range(adm.MEMBER_BURST))
    assert n == adm.MEMBER_BURST - adm.GUEST_BURST


def test_buckets_are_bounded_and_members_are_kept(monkeypatch):
    monkeypatch.setattr(adm, "MAX_SENDERS", 8)
    a = Admission(lambda s: s == "a0", clock=Clock())
    a.admit("a0", 1)
    for i in range(100):
        a.admit(f"x{i}", 1)
    assert len(a.buckets) == 8 and "a0" in a.buckets


def test_the_inbox_gate_refuses_before_copying_out_of_zenoh():
    inbox = Inbox(maxsize=10)
    seen: list = []
    inbox.gates["transitions"] = lambda key, size: seen.append((key, size)) or key.endswith("/a0/transitions")

    class Payload(bytes):
        def to_bytes(self) -> bytes:
            assert self.startswith(b"ok"), "a refused payload was copied"
            return bytes(self)

    cb = inbox.callback("transitions")
    cb(SimpleNamespace(payload=Payload(b"no"), key_expr=RUN.transitions("x9")))
    cb(SimpleNamespace(payload=Payload(b"ok!"), key_expr=RUN.transitions("a0")))
    assert [k for k, _ in seen] == [RUN.transitions("x9"), RUN.transitions("a0")] and seen[1][1] == 3
    item = inbox.get()
    assert item[:3] == ("transitions", RUN.transitions("a0"), b"ok!") and inbox.get() is None


def test_a_flooding_sender_stores_nothing_while_the_honest_one_goes_on(tmp_path, monkeypatch):
    monkeypatch.setattr(adm, "GUEST_BURST", 8)
    monkeypatch.setattr(adm, "MEMBER_BURST", 16)
    loop, _ = make_loop(tmp_path)
    ing = loop.ingest
    ing.admission.clock = Clock()  # (no refill: the flood is instantaneous)
    ing.lead_cap = 16
    key = RUN.transitions("f9")
    at_refusal = None
    for seq in range(216):  # in order, far faster than the budget refills
        p = _payload(seq, "f9")
        if ing.admit(key, len(p)):
            ing.receive("transitions", key, p)
        elif at_refusal is None:
            at_refusal = ing.streams["f9"].ingested
    st = ing.streams["f9"]
    assert ing.admission.penalized("f9") and st.pending  # (batches over f9's lead cap: deferred, held)
    loop.ack_all()  # (what training does after each iteration: releases what fits, drops a flood's)
    assert st.ingested == at_refusal and not st.pending, (at_refusal, st.ingested, len(st.pending))
    by = ing.rejects.by_kind()
    assert by["over_budget"] == 216 - 16 - 4, by  # (8 as a guest, 8 as a member, 4 refunds)
    for seq in range(2):  # the honest actor (its lead cap: 16): its batches are admitted, accepted and refunded
        p = _payload(seq, "a0")
        assert ing.admit(RUN.transitions("a0"), len(p))
        ing.receive("transitions", RUN.transitions("a0"), p)
    assert ing.streams["a0"].ingested == 16 and not ing.admission.penalized("a0")
    held = ing.streams["f9"].next_seq
    ing.receive("transitions", key, _payload(held, "f9"))  # let through by the refill, while penalized: not taken
    assert ing.streams["f9"].next_seq == held and ing.results["over_budget"] >= 1


def test_a_penalized_sender_gets_nothing_released_and_loses_what_it_held(tmp_path):
    loop, _ = make_loop(tmp_path)
    ing = loop.ingest
    ing.lead_cap = 16
    for seq in range(8):
        ing.offer(batch(seq, 8 * seq, 8, actor="a1", stream="s1"))
    st = ing.streams["a1"]
    n = st.next_seq
    assert n < 8 and n in st.pending  # deferred: over the lead cap (training has not caught up)
    ing.room = lambda st: 1000  # training made room
    ing.admission.refused_at["a1"] = -1e9  # a refusal long ago: no penalty now
    assert ing.release() and st.next_seq == 8 and not st.pending
    ing.offer(batch(9, 72, 8, actor="a1", stream="s1"))  # held: not in order
    ing.offer(batch(8, 64, 8, actor="a1", stream="s1"))
    ing.offer(batch(11, 88, 8, actor="a1", stream="s1"))
    ing.offer(batch(10, 80, 8, actor="a1", stream="s1"))
    assert st.next_seq == 12 and not st.pending
    ing.offer(batch(13, 104, 8, actor="a1", stream="s1"))
    ing.admission.refused_at["a1"] = ing.admission.clock()  # refused just now
    ing.offer(batch(12, 96, 8, actor="a1", stream="s1"))  # (offer itself: the gate and receive see the budget)
    assert st.next_seq == 14
    ing.offer(batch(15, 120, 8, actor="a1", stream="s1"))
    assert 15 in st.pending
    assert not ing.release() and not st.pending and st.next_seq == 14
