"""RLPD's symmetric sampling in the learner's replay buffer (learner/replay.py, ``--sampling rlpd``): half of each
minibatch from the intervened (prior) slots within what may be sampled, the rest uniform; SB3's uniform sampling
unchanged draw for draw; the counters kept through a pickle and a checkpoint; what the status and the log say."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from khgrl.common.config.settings import TQCSettings
from khgrl.common.tasks.spaces import action_space, observation_space
from khgrl.common.wire.status import LearnerInfo
from khgrl.learner.replay import PRIOR_FRACTIONS, StreamReplayBuffer, prior_fraction
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.save_util import load_from_pkl, save_to_pkl

OBS, ACT = observation_space(), action_space()
SMALL = TQCSettings(learning_starts=16, buffer_size=200, net_arch=(16, 16), batch_size=8, gradient_steps=2)


def _fill(rb, n: int, prior=(), start: int = 0) -> None:
    """``n`` transitions whose observation's first value is their running index (so a sample shows its slot
    while the buffer has not wrapped); those in ``prior`` intervened."""
    idx = np.arange(start, start + n)
    obs = np.zeros((n, 5), np.float32)
    obs[:, 0] = idx
    flags = np.isin(idx, list(prior)).astype(np.uint8)
    zeros = np.zeros(n, np.float32)
    rb.add_batch(obs, obs, np.zeros((n, 2), np.float32), zeros, zeros, zeros, intervened=flags,
                 clipped=np.zeros(n, np.uint8), actor=0, first_step=start)


def _drawn(rb, batch: int, seed: int = 0) -> np.ndarray:
    np.random.seed(seed)
    return rb.sample(batch).observations[:, 0].numpy().astype(int)


def test_the_fractions_and_their_check():
    assert PRIOR_FRACTIONS == {"uniform": 0.0, "rlpd": 0.5} and prior_fraction("rlpd") == 0.5
    with pytest.raises(ValueError, match="unknown sampling"):
        prior_fraction("per")
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        StreamReplayBuffer(10, OBS, ACT, prior_fraction=1.5)
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        StreamReplayBuffer(10, OBS, ACT, prior_fraction=0.5, optimize_memory_usage=True,
                           handle_timeout_termination=False)


@pytest.mark.parametrize("stored", [30, 64])  # not full, full (and wrapped)
def test_uniform_sampling_draws_exactly_what_sb3s_buffer_draws(stored):
    ours, ref = StreamReplayBuffer(40, OBS, ACT), ReplayBuffer(40, OBS, ACT)
    rng = np.random.default_rng(1)
    for i in range(stored):
        obs = rng.random((1, 5), dtype=np.float32)
        ours.add(obs, obs, np.zeros((1, 2), np.float32), np.array([i], np.float32), np.zeros(1), [{}],
                 intervened=i % 3 == 0)
        ref.add(obs, obs, np.zeros((1, 2), np.float32), np.array([i], np.float32), np.zeros(1), [{}])
    for seed in range(3):
        np.random.seed(seed)
        a = ours.sample(16)
        np.random.seed(seed)
        b = ref.sample(16)
        assert np.array_equal(a.rewards.numpy(), b.rewards.numpy())
    assert (ours.sampled_prior, ours.sampled_online, ours.prior_share) == (0, 48, 0.0)


def test_uniform_sampling_leaves_the_global_random_state_as_sb3s_does():
    ours, ref = StreamReplayBuffer(40, OBS, ACT, prior_fraction=0.0), ReplayBuffer(40, OBS, ACT)
    for rb in (ours, ref):
        for i in range(10):
            rb.add(np.zeros((1, 5)), np.zeros((1, 5)), np.zeros((1, 2)), np.zeros(1), np.zeros(1), [{}])
    np.random.seed(5)
    ours.sample(8)
    after_ours = np.random.rand()
    np.random.seed(5)
    ref.sample(8)
    assert np.random.rand() == after_ours  # no extra draw


def test_rlpd_draws_half_the_batch_from_the_intervened_slots():
    rb = StreamReplayBuffer(1000, OBS, ACT, prior_fraction=0.5)
    prior = set(range(0, 300, 10))
    _fill(rb, 300, prior)
    assert rb.prior_slots() == 30 and rb.prior_index().tolist() == sorted(prior)
    for batch, n_prior in ((256, 128), (255, 128), (9, 4)):  # round(B / 2): 127.5 -> 128, 4.5 -> 4
        before = rb.sampled_prior
        slots = _drawn(rb, batch)
        assert set(slots[batch - n_prior:]) <= prior  # the prior part (after the online part)
        assert rb.sampled_prior - before == n_prior
    assert rb.sampled_online == 128 + 127 + 5 and rb.prior_share == pytest.approx((128 + 128 + 4) / 520)
    online = np.concatenate([_drawn(rb, 256, seed)[:128] for seed in range(10)])
    assert 0.03 < np.isin(online, list(prior)).mean() < 0.2  # uniform over all slots: about 1 in 10
    drawn = np.concatenate([_drawn(rb, 256, seed)[128:] for seed in range(10)])
    assert set(drawn) == prior  # every prior slot is drawn


def test_rlpd_respects_the_sample_limit_in_both_parts():
    rb = StreamReplayBuffer(1000, OBS, ACT, prior_fraction=0.5)
    _fill(rb, 300, {50, 99, 100, 250})
    rb.sample_limit = 100  # an iteration due at transition 100: slots 0..99
    slots = np.concatenate([_drawn(rb, 64, seed) for seed in range(20)])
    assert slots.max() < 100 and set(slots.reshape(20, 64)[:, 32:].ravel()) == {50, 99}
    rb.sample_limit = 50  # no prior slot below it: the whole batch online, drawn as the uniform buffer draws
    before = rb.sampled_prior
    uniform = StreamReplayBuffer(1000, OBS, ACT)
    _fill(uniform, 300, {50, 99, 100, 250})
    uniform.sample_limit = 50
    assert np.array_equal(_drawn(rb, 64, 3), _drawn(uniform, 64, 3)) and rb.sampled_prior == before
    assert _drawn(rb, 64).max() < 50


def test_rlpd_without_prior_data_samples_as_uniform_does():
    rb, uniform = StreamReplayBuffer(100, OBS, ACT, prior_fraction=0.5), StreamReplayBuffer(100, OBS, ACT)
    for b in (rb, uniform):
        _fill(b, 60)
    assert np.array_equal(_drawn(rb, 32, 7), _drawn(uniform, 32, 7))
    assert (rb.sampled_prior, rb.sampled_online) == (0, 32)
    _fill(rb, 1, {60}, start=60)  # the first prior transition: from now on half of each batch
    assert (_drawn(rb, 32)[16:] == 60).all() and rb.sampled_prior == 16


def test_rlpd_on_a_full_buffer_samples_every_slot_and_the_index_follows_overwrites():
    rb = StreamReplayBuffer(50, OBS, ACT, prior_fraction=0.5)
    _fill(rb, 50, {3, 40})
    assert rb.full and rb.prior_index().tolist() == [3, 40]
    rb.sample_limit = 10  # (a full buffer samples everything, as SB3's)
    assert set(_drawn(rb, 64)[32:]) == {3, 40}
    _fill(rb, 5, {52}, start=50)  # overwrites slots 0..4: slot 3 is no longer prior, slot 2 is
    assert rb.prior_index().tolist() == [2, 40] and rb.prior_slots() == 2
    assert set(_drawn(rb, 64)[32:]) == {52, 40}


def test_the_counters_survive_a_pickle_and_older_buffers_load(tmp_path):
    rb = StreamReplayBuffer(100, OBS, ACT, prior_fraction=0.5)
    _fill(rb, 40, {1, 2})
    _drawn(rb, 16)
    rb.prior_index()
    save_to_pkl(tmp_path / "rb.pkl", rb)
    again = load_from_pkl(tmp_path / "rb.pkl")
    assert (again.prior_fraction, again.sampled_prior, again.sampled_online) == (0.5, 8, 8)
    assert again._prior_index is None and again.prior_index().tolist() == [1, 2]
    old = rb.__getstate__()
    for name in ("prior_fraction", "sampled_prior", "sampled_online", "_writes"):
        del old[name]  # a buffer pickled by a learner before RLPD sampling
    older = StreamReplayBuffer.__new__(StreamReplayBuffer)
    older.__setstate__(pickle.loads(pickle.dumps(old)))
    assert (older.prior_fraction, older.sampled_prior, older.sampled_online) == (0.0, 0, 0)
    assert _drawn(older, 8).max() < 40


def test_the_learner_builds_and_loads_its_buffer_with_the_runs_sampling(tmp_path):
    from khgrl.learner.checkpoint import save_checkpoint
    from khgrl.learner.resume import open_learner

    rlpd = TQCSettings(**{**SMALL.__dict__, "sampling": "rlpd"})
    uniform, _ = open_learner(SMALL, 1, tmp_path / "u", resume=False, logger_formats=("csv",), algo="sac")
    assert uniform.buffer.prior_fraction == 0.0 and uniform.algo.model.replay_buffer_kwargs == {}
    trainer, streams = open_learner(rlpd, 1, tmp_path / "learner", resume=False, logger_formats=("csv",), algo="sac")
    assert trainer.buffer.prior_fraction == 0.5
    _fill(trainer.buffer, 40, {5, 6, 7})
    trainer.algo.train(2, timestep=24, sample_limit=24)
    assert (trainer.buffer.sampled_prior, trainer.buffer.sampled_online) == (8, 8)
    state = trainer.state()
    assert state["sampled"] == {"prior": 8, "online": 8}
    save_checkpoint(tmp_path / "learner", trainer.algo, {**state, **streams.state()})
    again, _ = open_learner(rlpd, 1, tmp_path / "learner", resume=True, logger_formats=("csv",), algo="sac")
    assert again.buffer.prior_fraction == 0.5 and (again.buffer.sampled_prior, again.buffer.sampled_online) == (8, 8)
    as_uniform, _ = open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",), algo="sac")
    assert as_uniform.buffer.prior_fraction == 0.0  # the current settings decide
    as_uniform.restore({**state, "sampled": {"prior": 3, "online": 5}})  # a newer model checkpoint's counters
    assert (as_uniform.buffer.sampled_prior, as_uniform.buffer.sampled_online) == (3, 5)


def test_the_scalar_log_and_the_status_report_the_prior_data(tmp_path):
    from khgrl.deploy.run.progress import ProgressView
    from khgrl.learner.resume import open_learner

    rlpd = TQCSettings(**{**SMALL.__dict__, "sampling": "rlpd"})
    trainer, _ = open_learner(rlpd, 1, tmp_path / "learner", resume=False, logger_formats=("csv",), algo="sac")
    _fill(trainer.buffer, 40, {5, 6, 7})
    trainer.algo.train(2, timestep=24, sample_limit=24)
    trainer.record_iteration(0.1, 0)
    header, row = (tmp_path / "learner" / "tb" / "progress.csv").read_text().splitlines()[:2]
    values = dict(zip(header.split(","), row.split(",")))
    assert float(values["learner/prior_share"]) == 0.5 and int(values["learner/prior_slots"]) == 3

    base = dict(id="learner", epoch="e", ingested=120, iterations=15, gradient_steps=96, grad_steps_per_s=12.4,
                version=3, pending_iterations=0, queue_depth=0, rejects={}, paused=False, checkpoints=0, next_seq={},
                durable={}, duplicates={}, weights_queries=0, utd=0.8)
    view = ProgressView([], 2, enabled=False)
    view.learner = LearnerInfo(**base)
    assert view.caption() == "learner: 120 transitions, 96 gradient steps (12/s), weights v3"  # uniform: as before
    view.learner = LearnerInfo(**base, prior_fraction=0.5, prior_slots=40, sampled_prior=384, sampled_online=384)
    assert view.caption() == ("learner: 120 transitions, 96 gradient steps (12/s), weights v3, UTD 0.80, prior: 40 "
                              "slots, 50% of samples")


def test_the_learner_status_carries_the_sampling_counters_through_the_wire(tmp_path):
    from types import SimpleNamespace

    from khgrl.common.delivery.ingest import StreamTable
    from khgrl.common.process import StopFlag
    from khgrl.common.wire.protocol import Status, decode, encode
    from khgrl.learner.loop import LearnerLoop
    from khgrl.learner.resume import open_learner

    rlpd = TQCSettings(**{**SMALL.__dict__, "sampling": "rlpd"})
    trainer, _ = open_learner(rlpd, 1, tmp_path / "learner", resume=False, logger_formats=("csv",), algo="sac")
    loop = LearnerLoop(trainer, StreamTable(), SimpleNamespace(queries=0), learner_id="L1",
                       learner_dir=tmp_path / "learner", checkpoint_every=0, flag=StopFlag())
    _fill(trainer.buffer, 40, {5, 6, 7})
    trainer.algo.train(2, timestep=24, sample_limit=24)
    info = decode(Status, encode(Status(role="learner", info=loop.info()), "L1", 1)).info
    assert (info.prior_fraction, info.prior_slots, info.sampled_prior, info.sampled_online) == (0.5, 3, 8, 8)
