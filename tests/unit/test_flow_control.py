"""Flow control and the learner's ingest apart from training: the actor's window of batches out, re-sends of only
the window with backoff, the replay buffer's sample limit, robot mode, and ingest that never waits for a
gradient step."""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from khgrl.actor.weights import PolicyWeights, WeightsReceiver
from khgrl.common.config.settings import StreamSettings
from khgrl.common.delivery.actor_side import ActorDelivery
from khgrl.common.delivery.ingest import FairInbox
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.stream import MAX_RESEND_AFTER_S, TransitionStream
from khgrl.common.delivery.transport import Inbox
from khgrl.common.process import StopFlag
from khgrl.common.wire.checks import RejectCounter
from khgrl.common.wire.protocol import Ack, Control, Transitions, decode, encode
from khgrl.learner.loop import LearnerLoop
from khgrl.learner.replay import SIDE_ARRAYS
from khgrl.learner.resume import open_learner

from test_actor_parts import Clock, collect
from test_learner_parts import RUN, SMALL, Collect, batch, make_loop


def _stream(tmp_path, window: int):
    sent: list[bytes] = []
    clock = Clock()
    stream = TransitionStream("a0", "s1", Outbox(1000, tmp_path / "outbox"), sent.append, RejectCounter("a0"),
                              resend_after_s=2.0, clock=clock, window=window, task="0123456789abcdef")
    return stream, sent, clock


def _seqs(sent: list[bytes]) -> list[int]:
    return [decode(Transitions, p).envelope.seq for p in sent]


def _ack(received: int, durable: int = -1, epoch: str = "e1") -> Ack:
    return Ack(actor="a0", received=received, durable=durable, trained=0, version=0, epoch=epoch, stream="s1")


def test_at_most_the_window_is_out_and_the_rest_goes_as_acks_come(tmp_path):
    stream, sent, _ = _stream(tmp_path, window=2)
    collect(stream, 8 * 6)  # seqs 0..5
    assert _seqs(sent) == [0, 1] and stream.sent == 16 and len(stream.outbox) == 6
    assert stream.on_ack(_ack(0))
    assert _seqs(sent) == [0, 1, 2]  # received 0: 1 and 2 are out
    assert not stream.on_ack(_ack(3))  # beyond what was published: refused
    assert stream.refused_acks == 1 and _seqs(sent) == [0, 1, 2]
    assert stream.on_ack(_ack(2))
    assert _seqs(sent) == [0, 1, 2, 3, 4] and stream.sent == 40
    held_back = decode(Transitions, sent[-1])
    assert held_back.base_seq == 0 and held_back.first_step == 32
    assert stream.on_ack(_ack(4, durable=4))
    assert _seqs(sent)[-1] == 5 and decode(Transitions, sent[-1]).base_seq == 5  # re-stamped: 0..4 are gone


def test_a_stall_resends_only_the_window_and_backs_off(tmp_path):
    stream, sent, clock = _stream(tmp_path, window=3)
    collect(stream, 8 * 10)
    assert _seqs(sent) == [0, 1, 2]
    sent.clear()
    waits = []
    for _ in range(6):  # the learner is alive but never acks
        t0 = clock.t
        while not sent:
            clock.t += 0.25
            stream.check_resend(learner_alive=True)
        waits.append(clock.t - t0)
        assert _seqs(sent) == [0, 1, 2]  # only the window, every time
        sent.clear()
    assert waits[0] == pytest.approx(2.25) and waits[1] == pytest.approx(4.25) and waits[2] == pytest.approx(8.25)
    assert max(waits) <= MAX_RESEND_AFTER_S + 0.25 and stream.resends == 6
    stream.on_ack(_ack(1))  # progress: the backoff starts over
    assert _seqs(sent) == [3, 4] and stream.stalls == 0


def test_a_new_learner_epoch_gets_the_window_after_what_it_holds(tmp_path):
    stream, sent, _ = _stream(tmp_path, window=2)
    collect(stream, 8 * 6)
    stream.on_ack(_ack(1))
    stream.on_ack(_ack(3))
    sent.clear()
    stream.on_ack(_ack(0, durable=0, epoch="e2"))  # restarted from a checkpoint holding seq 0
    assert _seqs(sent) == [1, 2] and stream.resent_batches == 2
    stream.on_ack(_ack(2, durable=0, epoch="e2"))
    assert _seqs(sent) == [1, 2, 3, 4]


def test_an_episode_ending_off_the_training_grid_keeps_the_first_iteration_in_lock_step(tmp_path):
    """Fetch: 100-step episodes, learning_starts 100, train_freq 8. The episode's last, short batch (96..99) made the
    ack say 100 trained, so the actor ran up to 107 before waiting: step 104, the first due iteration's, took the
    initial weights whenever the ack of the batch that made it due (100..103) came late. Here: learning_starts 20,
    an episode of 20 steps, the first iteration due at 24; the real actor stream and learner loop, acks in hand."""
    loop, pub = make_loop(tmp_path, tqc=replace(SMALL, learning_starts=20))
    stream, sent, _ = _stream(tmp_path, window=64)
    weights = PolicyWeights(None, "a0", WeightsReceiver(None, {}, RejectCounter("a0"), "weights"))
    weights.epoch, weights.version = loop.trainer.epoch, 0  # the actor runs the learner's initial weights
    inbound = SimpleNamespace(paused=False, learners={"learner"})  # the learner is alive
    delivery = ActorDelivery("a0", None, None, stream, weights, StreamSettings(), StopFlag(), inbound, print, print)

    def deliver_and_ack() -> None:  # what the actor published reaches the learner, the learner's acks the actor
        for payload in sent:
            loop.offer(decode(Transitions, payload))
        sent.clear()
        loop.ingest.ack_touched()
        for msg in pub.of(Ack):
            stream.on_ack(msg)
        pub.sent.clear()

    def steps(n: int, episode_end: int | None = None, deliver: bool = True) -> None:  # the actor's loop: cut every
        # 8 and at episode end
        for _ in range(n):
            assert not delivery.must_wait(), f"step {stream.count}"  # inside learning_starts: no waiting
            i = stream.count
            obs = np.full(5, i, dtype=np.float32)
            stream.add(obs, obs + 1, np.array([0.5, -0.5], np.float32), 0.0, False, stream.count + 1 == episode_end,
                       False, False)
            if stream.count % 8 == 0 or stream.count == episode_end:
                stream.cut()
            if deliver:
                deliver_and_ack()

    steps(20, episode_end=20)  # episode 1: batches 0..7, 8..15, 16..19
    assert stream.sent == 20
    steps(3)
    steps(1, deliver=False)  # 20..23: the batch that makes the first iteration due (at 24) is out, not yet acked
    assert stream.sent == 24
    # its ack comes late: step 24 waits all the same (trained 16, on the grid; 20 let the actor run on to 27)
    assert delivery.must_wait(), f"step 24 taken with the initial weights: acked trained {stream.trained}"
    deliver_and_ack()
    assert [at for at, _ in loop.trainer.due] == [24] and stream.trained == 0 and delivery.must_wait()
    loop.step()  # the iteration: weights version 1, trained on 24
    for msg in pub.of(Ack):
        stream.on_ack(msg)
    assert stream.trained == 24 and stream.ack_version == 1 and delivery.must_wait()  # until version 1 is loaded
    weights.version = 1
    assert not delivery.must_wait()


def test_sample_limit_keeps_an_iteration_on_the_data_it_was_due_at(tmp_path):
    trainer, _ = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    rb = trainer.buffer
    for i in range(100):
        rb.add(np.full((1, 5), i, np.float32), np.zeros((1, 5)), np.zeros((1, 2)), np.zeros(1), np.zeros(1), [{}])
    rb.sample_limit = 40
    assert rb.sample(2000).observations.max().item() == 39
    rb.sample_limit = None
    assert rb.sample(2000).observations.max().item() == 99


def test_robot_mode_trains_whenever_free_and_reports_its_update_to_data_ratio(tmp_path):
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    pub = Collect()
    loop = LearnerLoop(trainer, streams, pub, learner_id="L", learner_dir=tmp_path / "learner", checkpoint_every=0,
                       flag=StopFlag(), mode="robot")
    for seq in range(4):
        loop.offer(batch(seq, 8 * seq, 8))
    assert not trainer.due  # no schedule in robot mode
    for _ in range(5):
        assert loop.work()
    assert trainer.iterations == 5 and trainer.utd == pytest.approx(5 * SMALL.gradient_steps / (32 - 16))
    assert loop.info().mode == "robot" and loop.info().utd == pytest.approx(trainer.utd, abs=1e-3)
    assert loop.info().rss_mb > 10
    assert loop.info().not_admitted_dropped == 0
    loop.inbox = FairInbox(Inbox(), lambda actor: False)
    loop.inbox.dropped = 7  # batches of ids not admitted yet, dropped over the caps: in the status, not only at the end
    assert loop.info().not_admitted_dropped == 7


def test_ingest_never_waits_for_a_gradient_step(tmp_path):
    """While an iteration takes long (a slow GPU, a big network), batches keep going into the buffer and are acked."""
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    pub = Collect()
    loop = LearnerLoop(trainer, streams, pub, learner_id="L", learner_dir=tmp_path / "learner", checkpoint_every=0,
                       flag=StopFlag())
    training = threading.Event()
    real_train = trainer.algo.model.train

    def slow_train(**kw):
        training.set()
        time.sleep(1.5)
        real_train(**kw)

    trainer.algo.model.train = slow_train
    inbox = Inbox(maxsize=1000)
    runner = threading.Thread(target=loop.run, args=(inbox,))
    runner.start()
    try:
        for seq in range(3):  # 24 > learning_starts: an iteration comes due and starts
            inbox.put(("transitions", RUN.transitions("a0"), encode(batch(seq, 8 * seq, 8), "a0", seq), 0.0))
        assert training.wait(10.0)
        t0 = time.monotonic()
        for seq in range(3, 40):
            inbox.put(("transitions", RUN.transitions("a0"), encode(batch(seq, 8 * seq, 8), "a0", seq), 0.0))
        while trainer.total < 320 and time.monotonic() - t0 < 1.0:
            time.sleep(0.01)
        assert trainer.total == 320 and trainer.iterations == 0  # all stored while the first iteration ran
        assert max(a.received for a in pub.of(Ack)) == 39
    finally:
        inbox.put(("control", RUN.control("learner"), encode(Control(command="stop"), "launcher", 0), 0.0))
        runner.join(30.0)
    assert not runner.is_alive() and trainer.iterations >= 1


def test_add_batch_fills_the_buffer_exactly_as_transition_by_transition_adds(tmp_path):
    """The vectorised store (ingest speed) gives the same slots, values, flags and provenance as SB3's add, also
    when it wraps around a full buffer; and the same due iterations."""
    from khgrl.common.config.settings import TQCSettings

    tqc = TQCSettings(learning_starts=5, buffer_size=50, net_arch=(8,), batch_size=4)
    a, _ = open_learner(tqc, 1, tmp_path / "a", resume=False, logger_formats=("csv",))
    b, _ = open_learner(tqc, 1, tmp_path / "b", resume=False, logger_formats=("csv",))
    rng = np.random.default_rng(3)
    first = 0
    for n in (7, 13, 1, 29, 8, 17):  # 75 transitions: the 50-slot buffer wraps
        obs = rng.normal(size=(n, 5)).astype(np.float32)
        nxt, act = rng.normal(size=(n, 5)).astype(np.float32), rng.uniform(-1, 1, (n, 2)).astype(np.float32)
        rew = rng.normal(size=n).astype(np.float32)
        term, trunc = rng.random(n) < 0.1, rng.random(n) < 0.1
        iv, cl = (rng.random(n) < 0.5).astype(np.uint8), (rng.random(n) < 0.5).astype(np.uint8)
        for i in range(n):
            info = [{"TimeLimit.truncated": bool(trunc[i] and not term[i])}]
            a.buffer.add(obs[i][None], nxt[i][None], act[i][None], rew[i:i + 1],
                         np.array([term[i] or trunc[i]], np.float32), info, intervened=iv[i], clipped=cl[i], actor=2,
                         step=first + i)
        b.buffer.add_batch(obs, nxt, act, rew, (term | trunc).astype(np.float32), (trunc & ~term).astype(np.float32),
                           intervened=iv, clipped=cl, actor=2, first_step=first)
        first += n
    assert (a.buffer.pos, a.buffer.full) == (b.buffer.pos, b.buffer.full) == (25, True)
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts", *SIDE_ARRAYS):
        np.testing.assert_array_equal(getattr(a.buffer, name), getattr(b.buffer, name), err_msg=name)


def test_due_iterations_of_a_batch_match_the_per_transition_schedule(tmp_path):
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    loop = LearnerLoop(trainer, streams, Collect(), learner_id="L", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag())
    loop.offer(batch(0, 0, 13, actor="a0"))
    loop.offer(batch(0, 0, 20, actor="a1", stream="s1"))
    loop.offer(batch(1, 13, 30, actor="a0"))
    # learning_starts 16, train_freq 8: due at 24, 32, ..., 56 of 63 transitions; a1 stored 20 at 33
    assert [at for at, _ in trainer.due] == [24, 32, 40, 48, 56]
    assert [snap for _, snap in trainer.due] == [{"a0": 13, "a1": 11}, {"a0": 13, "a1": 19}, {"a0": 20, "a1": 20},
                                                 {"a0": 28, "a1": 20}, {"a0": 36, "a1": 20}]
    assert streams["a0"].index == 43 and streams["a0"].ingested == 43 and trainer.total == 63
