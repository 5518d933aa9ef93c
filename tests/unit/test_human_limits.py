"""Bounds on a human-input client (issue 21, docs/protocol.md "Limits on human clients"): assignments, P_h far
outside the workspace, the holding allowance, pauses that expire, lock-step clients that skip a step."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.actor.arbiter import CorrectionArbiter
from khgrl.actor.human_limits import Assignments, HoldAllowance, HumanPauses, far_outside
from khgrl.common.config.settings import parse_assignments

WS = (np.zeros(2), np.ones(2))


def corr(client="h", active=True, p=(0.5, 0.5), episode=1, step=None, actor="a0"):
    from khgrl.common.wire.messages import Correction

    return Correction(client=client, actor=actor, active=active, p_h=np.array(p, float) if active else None,
                      episode=episode, step=step)


def test_assignments_parse_and_refuse():
    assert parse_assignments("") is None
    assert parse_assignments("h0=a0,a1; user=a0 s=*") == {"h0": {"a0", "a1"}, "user": {"a0"}, "s": {"*"}}
    for bad in ("h0", "=a0", "h0=", "h/0=a0"):
        with pytest.raises(ValueError):
            parse_assignments(bad)
    a1 = Assignments("a1", "h0=a0,a1;user=a0;s=*")
    assert a1.allows("h0") and a1.allows("s") and not a1.allows("user") and not a1.allows("other")
    assert Assignments("a1").allows("anyone")
    arb = CorrectionArbiter("a1", 0.5, True, assignments=a1)
    why = arb.offer(corr("user", actor="a1"), 0.0, 1)
    assert "not assigned" in why and arb.current(0.1) is None and arb.counts["not_assigned"] == 1
    assert arb.offer(corr("h0", actor="a1"), 0.0, 1) is None and arb.current(0.1) is not None


def test_p_h_far_outside_is_refused_not_projected():
    assert far_outside(np.array([1.05, -0.09]), *WS) is None  # within 10 % of the extent: projected as before
    assert "outside" in far_outside(np.array([1.2, 0.5]), *WS)
    arb = CorrectionArbiter("a0", 0.5, True, workspace=WS)
    for p in ((1e300, -1e300), (-1e300, 0.5), (0.5, 1.11)):
        assert "refused" in arb.offer(corr(p=p), 0.0, 1)
        assert arb.holder is None and arb.current(0.01) is None
    assert arb.counts["far_outside"] == 3 and arb.counts["applied"] == 0
    assert "refused" in arb.offer(corr(p=(1e300, 0.5), step=3), 0.0, 1, 3)  # a lock-step word too
    assert arb.lockstep is None


def test_hold_allowance_bounds_the_share_of_a_long_run():
    """A client answering every step holds at most capacity + refill * (time not holding) of the running time."""
    arb = CorrectionArbiter("a0", 0.5, True, allowance=HoldAllowance(2.0, 0.5))
    held = steps = 0
    dt = 0.05
    for i in range(2000):  # 100 s of running time at 20 Hz, with a 10 s pause in the middle (not running time)
        now = i * dt + (10.0 if i >= 1000 else 0.0)
        if i == 1000:
            arb.extend(10.0)
        arb.offer(corr(), now, 1)
        held += arb.current(now) is not None
        steps += 1
    share = held / steps
    # long run: at most refill / (1 + refill) = 1/3, plus the first full allowance (2 s of 100 s)
    assert 0.2 < share <= 1 / 3 + 0.02 + 0.01, share
    assert arb.counts["holds_expired"] >= 2 and arb.counts["holds_refused"] > 0
    # the longest hold is the capacity (2 s = 40 steps)
    unlimited = CorrectionArbiter("a0", 0.5, True)
    for i in range(100):
        unlimited.offer(corr(), i * dt, 1)
        assert unlimited.current(i * dt) is not None


def test_hold_allowance_spans_episodes_and_refills():
    al = HoldAllowance(10.0, 0.5)
    assert al.left("h", 0.0) == 10.0 and al.may_start("h", 0.0)
    assert al.spend("h", 10.0, 10.0) == 0.0 and not al.may_start("h", 10.0)
    assert al.left("h", 14.0) == pytest.approx(2.0) and not al.may_start("h", 14.0)
    assert al.may_start("h", 15.0) and al.left("h", 100.0) == 10.0


def test_human_pause_expires_unless_renewed():
    p = HumanPauses(60.0)
    p.pause("gui", 0.0)
    assert p.active(59.0)
    p.pause("gui", 50.0)  # renewed
    assert p.active(100.0) and not p.active(110.1) and p.expired == 1
    p.pause("a", 0.0)
    p.pause("b", 0.0)
    p.resume("a")  # a client lifts its own pause only
    assert p.active(1.0)
    assert HumanPauses(0.0).limit == 0.0


def test_lockstep_word_one_step_ahead_is_given_up_at_once_and_backs_off():
    """A client whose words are one step ahead (answers frame t with step t + 2) skips every step: the actor gives it
    up at once (no wait), and does not wait for it again this episode nor, after repeated give-ups, for longer."""
    arb = CorrectionArbiter("a0", 0.5, True)
    timeouts = []
    for episode in range(1, 9):
        arb.new_episode(episode)
        for t in range(0, 50):
            arb.offer(corr("x", p=(0.5, 0.6), episode=episode, step=t + 2), 0.0, episode, t + 1)
            arb.ready(t + 1)  # never waits: the word for t + 2 came before any for t + 1
            arb.current(0.0, t + 1)
        timeouts.append(arb.counts["lockstep_timeouts"])
    # given up in episodes 1, 2, 4, 8 (after the n-th give-up, not waited for in the next 2**(n-1) - 1 episodes)
    assert timeouts == [1, 2, 2, 3, 3, 3, 3, 4], timeouts
    assert arb.counts["lockstep_skipped"] == 4


def test_inbound_bounds_fake_learner_tokens_and_human_pauses(tmp_path):
    """3,000 fake learner liveliness tokens: the actor follows at most MAX_LEARNERS (each new one costs a task query
    and an outbox re-send), the rest are refused and counted; a human pause from a client not assigned to the actor
    is refused, and one that is not renewed expires."""
    import time
    from types import SimpleNamespace

    from khgrl.actor.inbound import MAX_LEARNERS
    from khgrl.common.wire.messages import Control
    from khgrl.common.wire.protocol import encode

    from test_trust_checks import K, _inbound

    inbound, parts, _ = _inbound(tmp_path)
    queries = []
    parts.task = SimpleNamespace(digest="d")
    parts.link = SimpleNamespace(other_tasks=lambda task: queries.append(task) or {})
    for i in range(3000):
        inbound.handle("alive", f"khgrl/unit/alive/learner/fake{i}/e{i}", True, 0.0, episode=1)
    assert len(inbound.learners) == MAX_LEARNERS and len(queries) == MAX_LEARNERS
    assert parts.rejects.by_kind()["alive"] == 3000 - MAX_LEARNERS
    assert len(inbound.gate.alive) == MAX_LEARNERS
    for i in range(3000):  # gone again: only those followed mattered
        inbound.handle("alive", f"khgrl/unit/alive/learner/fake{i}/e{i}", False, 0.0, episode=1)
    assert not inbound.learners

    from khgrl.actor.human_limits import Assignments

    parts.arbiter.assignments = Assignments("a0", "gui=a0;other=a1")
    inbound.handle("human_request", K.human_request("other"), encode(Control(command="pause"), "other", 0),
                   time.monotonic(), episode=1)
    assert not inbound.paused and parts.rejects.by_kind()["control"] == 1
    inbound.handle("human_request", K.human_request("gui"), encode(Control(command="pause"), "gui", 0),
                   time.monotonic(), episode=1)
    assert inbound.paused
    inbound.handle("human_request", K.human_request("gui"), encode(Control(command="pause"), "gui", 1),
                   time.monotonic() - 61.0, episode=1)  # (as if last renewed 61 s ago)
    assert not inbound.paused and inbound.human_pauses.expired == 1


def test_the_gui_renews_its_pause(monkeypatch):
    """Actors end a human pause that is not renewed (human_pause_s, 60 s): the GUI asks again every PAUSE_RENEW_S
    while its pause is on, and stops when the person resumes."""
    from khgrl.human_bridge.gui import app as gui

    sent: list[str] = []
    a = gui.GuiApp(lambda *args: None, control=sent.append)
    clock = [1000.0]
    monkeypatch.setattr(gui.time, "monotonic", lambda: clock[0])
    a.toggle_pause()
    a.keepalive()
    assert sent == ["pause"]
    clock[0] += gui.PAUSE_RENEW_S
    a.keepalive()
    assert sent == ["pause", "pause"] and gui.PAUSE_RENEW_S < 60.0
    a.toggle_pause()
    clock[0] += 10 * gui.PAUSE_RENEW_S
    a.keepalive()
    assert sent == ["pause", "pause", "resume"]
