"""The actor's parts without Zenoh or an environment: correction arbitration, the outbox, the transition
stream (batches, acks, re-sends, forged acks), the weights bookkeeping, and the result files of a resumed run."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import threading

import numpy as np
import pytest
from khgrl.actor.arbiter import CorrectionArbiter
from khgrl.actor.pacing import Pacer, set_realtime
from khgrl.actor.record import CorrectionRecord
from khgrl.actor.results import EpisodeLog
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.stream import LEARNER_APPEARED_RESEND_S, TransitionStream
from khgrl.common.metrics import EpisodeStats
from khgrl.common.wire.checks import RejectCounter
from khgrl.common.wire.messages import Ack, Correction, Transitions
from khgrl.common.wire.protocol import decode


# ------------------------------------------------------------------------------------ arbiter
def live(client, active, p=(0.5, 0.5), actor="a0", episode=1) -> Correction:
    return Correction(client=client, actor=actor, active=active, p_h=np.array(p) if active else None, episode=episode)


def addressed(client, step, p=None, episode=1) -> Correction:
    return Correction(client=client, actor="a0", active=p is not None, p_h=None if p is None else np.array(p),
                      episode=episode, step=step)


def test_correction_arbitration():
    arb = CorrectionArbiter("a0", timeout=0.5, enabled=True)
    arb.offer(live("h1", True, (0.4, 0.6)), arrival=10.0, episode=1)
    arb.offer(live("h2", True, (0.9, 0.9)), arrival=10.1, episode=1)  # someone else: ignored
    arb.offer(live("h1", True, actor="a1"), arrival=10.1, episode=1)  # another actor's
    assert np.allclose(arb.current(10.2), [0.4, 0.6]) and arb.counts["ignored_other_client"] == 1
    assert arb.counts["ignored_other_actor"] == 1
    arb.extend(1.0)  # the actor paused for 1 s: the holder's silence does not count
    assert arb.current(11.3) is not None
    assert arb.current(11.7) is None and arb.counts["timeouts"] == 1  # silent > 0.5 s of running time
    arb.offer(live("h2", True, (0.9, 0.9)), arrival=12.0, episode=1)  # free again: h2 takes over
    arb.offer(live("h2", True, episode=0), arrival=12.1, episode=1)  # a frame of an old episode: stale
    assert np.allclose(arb.current(12.2), [0.9, 0.9]) and arb.counts["stale_episode"] == 1
    arb.offer(live("h2", False), arrival=12.3, episode=1)
    assert arb.current(12.3) is None
    kgrl = CorrectionArbiter("a0", timeout=0.5, enabled=False)
    kgrl.offer(live("h1", True), arrival=0.0, episode=1)
    assert kgrl.current(0.1) is None and kgrl.counts["ignored_method"] == 1


def test_live_hold_ends_with_its_episode():
    """A person still holding the robot when the episode ends does not drive step 0 of the next episode."""
    arb = CorrectionArbiter("a0", timeout=0.5, enabled=True)
    arb.new_episode(1)
    arb.offer(live("gui", True, (0.3, 0.7), episode=1), arrival=1.0, episode=1, step=40)
    assert np.allclose(arb.current(1.01, 41), [0.3, 0.7])
    arb.new_episode(2)  # well within the timeout
    assert arb.holder is None and arb.current(1.02, 0) is None
    assert arb.counts["episode_end_releases"] == 1 and arb.counts["releases"] == 1
    arb.offer(live("gui", True, (0.3, 0.7), episode=1), arrival=1.03, episode=2)  # still about episode 1: stale
    assert arb.current(1.04, 1) is None and arb.counts["stale_episode"] == 1
    arb.offer(live("other", True, (0.2, 0.2), episode=2), arrival=1.05, episode=2)  # the robot is free again
    assert np.allclose(arb.current(1.06, 2), [0.2, 0.2]) and arb.holder == "other"
    arb.new_episode(3)
    assert arb.counts["episode_end_releases"] == 2
    arb.new_episode(4)  # nothing held: nothing counted
    assert arb.counts["episode_end_releases"] == 2


def test_correction_arbitration_step_addressed():
    """A step-addressed client puts the actor in lock-step for the episode: each step waits for its word."""
    arb = CorrectionArbiter("a0", timeout=0.5, enabled=True)
    assert arb.ready(5)  # nobody in lock-step: never wait
    arb.offer(addressed("s", 5), arrival=1.0, episode=1, step=5)  # release word for step 5
    assert arb.lockstep == "s" and arb.ready(5) and not arb.ready(6)
    arb.offer(addressed("s", 6, (0.1, 0.2)), arrival=1.0, episode=1, step=5)  # early: kept for step 6
    assert arb.ready(5) and arb.ready(6) and arb.current(1.0, 5) is None
    assert np.allclose(arb.current(1.1, 6), [0.1, 0.2]) and arb.holder == "s"
    assert not arb.ready(7)  # waits for step 7's word...
    arb.offer(addressed("s", 6, (0.9, 0.9)), arrival=1.2, episode=1, step=7)  # ...one for a step already taken is late
    arb.offer(addressed("g", 7, (0.5, 0.5)), arrival=1.2, episode=1, step=7)  # another client: ignored
    arb.offer(addressed("s", 7, (0.3, 0.3), episode=2), arrival=1.2, episode=1, step=7)  # another episode: stale
    assert arb.counts["late_step"] == 1 and arb.counts["ignored_other_client"] == 1
    assert arb.counts["stale_episode"] == 1 and not arb.ready(7)
    arb.offer(addressed("s", 7, (0.3, 0.4)), arrival=1.3, episode=1, step=7)
    assert np.allclose(arb.current(5.0, 7), [0.3, 0.4])  # applied at its step, whatever the wall time
    arb.give_up(8)  # silent at step 8: plain mode again, the last P_h holds until the timeout
    assert arb.ready(8) and arb.counts["lockstep_timeouts"] == 1
    assert np.allclose(arb.current(5.1, 8), [0.3, 0.4]) and arb.current(5.6, 9) is None
    arb.offer(addressed("s", 3, (0.2, 0.2), episode=2), arrival=6.0, episode=2, step=3)
    assert np.allclose(arb.current(6.0, 3), [0.2, 0.2])
    arb.offer(addressed("s", 0, (0.6, 0.6), episode=3), arrival=6.0, episode=2, step=4)  # announces episode 3
    arb.new_episode(3)  # a lock-step hold ends with its episode; the announced client is in lock-step at once
    assert arb.holder is None and arb.lockstep == "s" and arb.ready(0) and not arb.ready(1)
    assert np.allclose(arb.current(6.1, 0), [0.6, 0.6])
    arb.offer(addressed("s", 1, episode=3), arrival=6.2, episode=3, step=1)
    assert arb.current(6.2, 1) is None and arb.counts["releases"] == 2  # the old hold at new_episode, this word
    arb.new_episode(4)  # no announcement: plain mode
    assert arb.lockstep is None and arb.ready(0)


# ------------------------------------------------------------------------------------- outbox
def test_outbox_spills_and_drops(tmp_path):
    box = Outbox(memory=3, spill_dir=tmp_path / "outbox")
    for s in range(8):
        box.add(s, f"batch{s}".encode(), n=s + 1)
    # written through: every batch has its file; 5 of them are no longer in memory as well
    assert len(box) == 8 and len(list((tmp_path / "outbox").iterdir())) == 8 and box.spilled_total == 5
    assert box.get(1) == b"batch1" and box.get(7) == b"batch7"
    assert box.seqs_after(4) == [5, 6, 7] and box.oldest() == 0 and box.newest() == 7
    assert box.transitions_after(4) == 6 + 7 + 8 and box.transitions_after(-1) == sum(range(1, 9))
    assert box.drop_through(5) == 6
    assert len(box) == 2 and box.oldest() == 6 and len(list((tmp_path / "outbox").iterdir())) == 2
    assert box.transitions_after(-1) == 7 + 8


# ------------------------------------------------------------------------------------- stream
class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def make_stream(tmp_path, memory: int = 1000):
    sent: list[bytes] = []
    clock = Clock()
    rejects = RejectCounter("actor/a0")
    stream = TransitionStream("a0", "s1", Outbox(memory, tmp_path / "outbox"), sent.append, rejects,
                              resend_after_s=2.0, clock=clock, task="0123456789abcdef")
    return stream, sent, clock, rejects


def collect(stream: TransitionStream, n: int, batch: int = 8, intervened: bool = False) -> None:
    for _ in range(n):
        i = stream.count
        obs = np.full(5, i, dtype=np.float32)
        stream.add(obs, obs + 1, np.array([0.5, -0.5], np.float32), float(i), False, False, intervened, False)
        if stream.count % batch == 0:
            stream.cut()


def ack(received: int, durable: int, epoch: str = "e1", stream: str | None = "s1", trained: int = 0,
        version: int = 0) -> Ack:
    return Ack(actor="a0", received=received, durable=durable, trained=trained, version=version, epoch=epoch,
               stream=stream)


def test_stream_cuts_numbered_batches(tmp_path):
    stream, sent, _, _ = make_stream(tmp_path)
    collect(stream, 20)
    stream.cut()  # the partial batch at episode end
    stream.cut()  # nothing collected: nothing sent
    batches = [decode(Transitions, p) for p in sent]
    assert [b.envelope.seq for b in batches] == [0, 1, 2] and [b.n for b in batches] == [8, 8, 4]
    assert [b.first_step for b in batches] == [0, 8, 16] and all(b.base_seq == 0 for b in batches)
    assert all(b.stream == "s1" and b.actor == "a0" for b in batches)
    assert batches[2].reward.tolist() == [16.0, 17.0, 18.0, 19.0]
    assert stream.sent == 20 and stream.highest_sent == 2 and stream.unconfirmed() == 20


def test_acks_drop_durable_batches_and_ignore_other_streams(tmp_path):
    stream, _, _, rejects = make_stream(tmp_path)
    collect(stream, 32)
    assert not stream.on_ack(ack(3, 3, stream="old"))  # an earlier incarnation's ack: not ours
    assert not stream.on_ack(ack(3, 3, stream=None))
    assert stream.durable == -1 and len(stream.outbox) == 4
    assert stream.on_ack(ack(3, 1, trained=16, version=2))
    assert (stream.received, stream.durable, stream.trained, stream.ack_version) == (3, 1, 16, 2)
    assert stream.outbox.seqs_after(-1) == [2, 3] and stream.unconfirmed() == 16
    assert rejects.by_kind() == {}


def test_forged_ack_beyond_what_was_sent_is_refused(tmp_path, caplog):
    """An ack claiming more than the actor has sent must not make it drop batches the learner does not hold."""
    stream, sent, _, rejects = make_stream(tmp_path)
    collect(stream, 24)  # seqs 0..2
    assert stream.on_ack(ack(0, 0))
    with caplog.at_level("WARNING"):
        assert not stream.on_ack(ack(2, 1_000_000))  # durable beyond seq 2
        assert not stream.on_ack(ack(7, 2))  # received beyond seq 2
        assert not stream.on_ack(ack(1_000_000, 1_000_000, epoch="forged"))
    assert stream.durable == 0 and stream.received == 0 and stream.ack_epoch == "e1"
    assert stream.outbox.seqs_after(-1) == [1, 2] and stream.unconfirmed() == 16
    assert stream.refused_acks == 3 and rejects.by_kind() == {"ack": 3}
    assert "ack claims batches beyond the highest seq sent" in caplog.text
    assert caplog.text.count("ack claims batches beyond the highest seq sent") == 1  # logged once, counted always
    n = len(sent)
    assert stream.on_ack(ack(2, 2))  # the truth is still believed
    assert stream.unconfirmed() == 0 and len(sent) == n
    assert stream.summary()["refused_acks"] == 3


def test_new_learner_epoch_resends_after_received_with_current_base_seq(tmp_path):
    stream, sent, _, _ = make_stream(tmp_path, memory=2)  # spilled batches are re-sent from disk
    collect(stream, 40)  # seqs 0..4
    stream.on_ack(ack(4, 1))
    sent.clear()
    stream.on_ack(ack(2, 1, epoch="e2"))  # the learner restarted from a checkpoint holding 0..2
    again = [decode(Transitions, p) for p in sent]
    assert [b.envelope.seq for b in again] == [3, 4] and all(b.base_seq == 2 for b in again)
    assert [b.first_step for b in again] == [24, 32] and stream.resends == 1 and stream.resent_batches == 2
    assert stream.checkpoint_requested_at == -1e9


def test_stall_and_learner_appearance_resend(tmp_path):
    stream, sent, clock, _ = make_stream(tmp_path)
    collect(stream, 16)
    sent.clear()
    clock.t += 1.0
    stream.check_resend(learner_alive=True)
    assert not sent  # not stalled yet
    clock.t += 1.5
    stream.check_resend(learner_alive=False)
    assert not sent  # nobody to re-send to
    stream.check_resend(learner_alive=True)
    assert [decode(Transitions, p).envelope.seq for p in sent] == [0, 1]
    sent.clear()
    stream.learner_appeared()  # a fresh learner: everything held, shortly, unless it acks first
    stream.check_resend(learner_alive=True)
    assert not sent
    clock.t += LEARNER_APPEARED_RESEND_S
    stream.check_resend(learner_alive=True)
    assert len(sent) == 2 and stream.resends == 2


def test_checkpoint_request_at_the_end(tmp_path):
    stream, _, clock, _ = make_stream(tmp_path)
    collect(stream, 16)
    assert not stream.checkpoint_due(learner_alive=True)  # the learner has not received everything
    stream.on_ack(ack(1, 0))
    assert not stream.checkpoint_due(learner_alive=False)
    assert stream.checkpoint_due(learner_alive=True) and not stream.checkpoint_due(learner_alive=True)
    clock.t += 5.1
    assert stream.checkpoint_due(learner_alive=True)
    assert not stream.all_durable()
    stream.on_ack(ack(1, 1))
    assert stream.all_durable() and stream.unconfirmed() == 0


# ------------------------------------------------------------------------------------ weights
def test_weights_parse_load_and_lag():
    import torch
    from khgrl.actor.weights import PolicyWeights, WeightsReceiver
    from khgrl.common.wire.checks import ProtocolError
    from khgrl.common.wire.messages import Weights
    from khgrl.common.wire.protocol import encode

    net = torch.nn.Linear(3, 2)

    class Policy:
        actor = net

        def load_weights(self, sd):
            net.load_state_dict(sd)

    rejects = RejectCounter("actor/a0")
    rx = WeightsReceiver(None, net.state_dict(), rejects, "k/weights")
    w = PolicyWeights(Policy(), "a0", rx)
    tensors = {"weight": np.ones((2, 3), np.float32), "bias": np.zeros(2, np.float32)}
    rx.offer(encode(Weights(version=3, trained={"a0": 24}, tensors=tensors, epoch="e1"), "learner", 0))
    rx.offer(encode(Weights(version=4, trained={}, tensors={"weight": np.ones((3, 3), np.float32),
                                                            "bias": np.zeros(2, np.float32)}), "learner", 1))
    assert rejects.by_kind() == {"weights": 1} and rx.received == 1
    assert w.behind("e1", 3) is True
    w.swap()
    assert (w.version, w.epoch, w.trained, w.swaps) == (3, "e1", 24, 1) and len(w.latency) == 1
    assert torch.all(net.weight == 1) and not w.behind("e1", 3) and w.behind("e2", 0) and not w.behind(None, 9)
    w.swap()  # nothing new
    assert w.swaps == 1
    assert not w.load(rx.parse(encode(Weights(version=2, trained={}, tensors=tensors, epoch="e1"), "learner", 2)))
    with pytest.raises(ProtocolError, match="names"):
        rx.parse(encode(Weights(version=5, trained={}, tensors={"weight": tensors["weight"]}), "learner", 3))
    for n in (24, 30, 40, 60):
        w.note_lag(n, max_lead=8)
    assert w.max_lag == 36 and w.lag_hist == {"0": 1, "6": 1, ">=16": 2}
    s = w.summary()
    assert s["weights"]["final_version"] == 3 and s["weights_latency_ms"]["n"] == 1


# ------------------------------------------------------------------------------- result files
def episode(n: int, steps: int = 10) -> EpisodeStats:
    return EpisodeStats(episode=n, steps=steps, ret=-1.5 * n, scale_max=[15.0, 15.0], wall_time=0.1)


def test_episode_log_resume_appends_and_continues_numbering(tmp_path):
    log = EpisodeLog(tmp_path, resume=False)
    assert log.last_episode == 0 and log.earlier_transitions == 0
    log.add(episode(1, 250))
    log.add(episode(2, 248))
    log.write_final({"episodes": 5}, {"episodes": 2})
    again = EpisodeLog(tmp_path, resume=True)
    assert again.last_episode == 2 and again.earlier_transitions == 498
    again.add(episode(3, 100))
    with open(tmp_path / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["episode"] for r in rows] == ["1", "2", "3"]  # one header, rows appended
    assert (tmp_path / "episodes.csv").read_text().count("episode,steps") == 1
    assert [e["episode"] for e in json.loads((tmp_path / "episodes.json").read_text())] == [1, 2, 3]
    fresh = EpisodeLog(tmp_path, resume=False)  # without --resume nothing is appended
    assert fresh.last_episode == 0 and not (tmp_path / "episodes.csv").exists()


def test_autonomous_success_looks_back_over_autonomous_episodes_only(tmp_path):
    """``--until-success``: the rate over the last N episodes without a human step, earlier parts included."""
    log = EpisodeLog(tmp_path, resume=False)
    log.add(dataclasses.replace(episode(1), success=True))
    log.add(dataclasses.replace(episode(2), success=False, intervention_steps=12))  # a human episode: not counted
    assert log.autonomous_success(2) is None  # one autonomous episode so far
    log.add(dataclasses.replace(episode(3), success=False))
    assert log.autonomous_success(2) == 0.5 and log.autonomous_success(1) == 0.0
    log.write_final({}, {})
    again = EpisodeLog(tmp_path, resume=True)  # a resumed part sees the earlier episodes
    again.add(dataclasses.replace(episode(4), success=True))
    assert again.autonomous_success(3) == 2 / 3 and again.autonomous_success(4) is None
    for rate, window in ((0.0, 1), (0.7, 3), (0.5, 4)):  # never asked, below the rate, too few episodes
        again.until = (rate, window)
        assert not again.converged() and not again.reached
    again.until = (0.6, 3)
    assert again.converged() and again.reached
    again.until = (0.9, 3)
    assert again.converged()  # (kept once reached)


def test_episode_log_resume_from_csv_only(tmp_path):
    """A part killed before episodes.json caught up: episodes.csv has the history."""
    log = EpisodeLog(tmp_path, resume=False)
    for n in (1, 2, 3):
        log.add(episode(n))
    (tmp_path / "episodes.json").unlink()
    again = EpisodeLog(tmp_path, resume=True)
    assert again.last_episode == 3 and again.earlier_transitions == 30
    assert again.earlier[0]["scale_max"] == [15.0, 15.0] and again.earlier[0]["success"] is False
    again.write_final({}, {})
    assert len(json.loads((tmp_path / "episodes.json").read_text())) == 3


def test_correction_record_appends_without_a_second_header(tmp_path):
    path = tmp_path / "corrections.csv"
    rec = CorrectionRecord(path, "r", "a0")
    rec.write(1, 5, "alice", np.array([0.25, 0.5]), {"projected": True})
    rec.close()
    rec = CorrectionRecord(path, "r", "a0", append=True)
    rec.write(4, 7, "bob", np.array([0.1, 0.2]), {"clipped": True})
    rec.close()
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["episode"], r["client"], r["projected"], r["clipped"]) for r in rows] == [
        ("1", "alice", "1", "0"), ("4", "bob", "0", "1")]
    CorrectionRecord(path, "r", "a0").close()  # without --resume: a fresh file
    assert path.read_text().splitlines() == [",".join(CorrectionRecord.FIELDS)]


# ------------------------------------------------------------------------------------- pacing
def test_pacer_without_rate_never_sleeps():
    pacer = Pacer(0.0)
    assert not pacer.sleep()
    pacer.step_started()
    pacer.step_started()
    assert len(pacer.periods) == 1


def test_set_realtime_is_reported_truthfully():
    """The control loop's SCHED_FIFO request either takes effect (root) or is refused and says so."""
    out = {}

    def loop_thread():
        before = os.sched_getscheduler(0)
        out["ok"] = set_realtime(7)
        out["policy"], out["prio"] = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
        out["before"] = before

    t = threading.Thread(target=loop_thread)
    t.start()
    t.join()
    if out["ok"]:
        assert out["policy"] == os.SCHED_FIFO and out["prio"] == 7
    else:
        assert out["policy"] == out["before"] != os.SCHED_FIFO
    assert os.sched_getscheduler(0) != os.SCHED_FIFO  # only the calling thread changed
