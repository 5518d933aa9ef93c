"""The learner watches its critic (issue 34 point 5, :mod:`khgrl.learner.critic_watch`): after a training iteration
whose critic's Q on the stored transitions goes beyond Q_max = 2 r_max / (1 - gamma), the iteration is rolled back
(restored exactly, as a non-finite one is) and counted (``q_rollbacks``); an ordinary iteration stands, and the check
draws no random numbers (a seeded run is unchanged). Before it, rewards near the old default bound (999,073) that
an actor holding the run's keys could store took the critic's Q on the honest actor's states to 2.4 million and
nothing noticed."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import TQCSettings
from khgrl.common.process import StopFlag
from khgrl.common.tasks.passage.env import PassageEnv
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import Transitions
from khgrl.common.wire.protocol import decode, encode
from khgrl.learner.critic_watch import CriticWatch, critic_values, q_limit
from khgrl.learner.loop import LearnerLoop, open_learner

SMALL = TQCSettings(learning_starts=16, buffer_size=1000, net_arch=(32, 32), batch_size=32)


@pytest.fixture(scope="module")
def task() -> TaskDescriptor:
    return PassageEnv("low_cov").descriptor("passage:low_cov")


class _Pub:
    queries = 0

    def __init__(self) -> None:
        self.sent: list = []

    def _keep(self, msg) -> None:
        self.sent.append(msg)

    weights = ack = status = _keep


def _loop(tmp_path: Path, task, algo: str = "tqc") -> LearnerLoop:
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",),
                                    task=task, algo=algo)
    loop = LearnerLoop(trainer, streams, _Pub(), learner_id="learner", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag())
    if task is not None:
        loop.set_task(task)
    return loop


def _feed(loop: LearnerLoop, task, seqs=range(4), n: int = 8) -> None:
    """Batches of a0 (ordinary values) past learning_starts: iterations come due."""
    for seq in seqs:
        rng = np.random.default_rng(seq)
        obs = rng.uniform(0, 1, (n, 5)).astype(np.float32)
        z = np.zeros(n, np.uint8)
        msg = Transitions(actor="a0", first_step=n * seq, obs=obs, next_obs=obs[::-1].copy(),
                          action=rng.uniform(-1, 1, (n, 2)).astype(np.float32),
                          reward=rng.normal(size=n).astype(np.float32), terminated=z, truncated=z, intervened=z,
                          clipped=z, base_seq=0, stream="s0", task=task.digest)
        loop.offer(decode(Transitions, encode(msg, "a0", seq)))


def _state(algo) -> dict[str, torch.Tensor]:
    snap = algo.snapshot()
    flat = {f"policy.{k}": v for k, v in snap["policy"].items()}
    for i, opt in enumerate(snap["optimizers"]):
        for p, st in opt["state"].items():
            flat.update({f"opt{i}.{p}.{k}": v for k, v in st.items()})
    return flat


def _last_bias(critic) -> torch.Tensor:
    """The output bias of the critics' first Q-network (TQC: its quantiles; SAC: its one Q)."""
    return [p for n, p in critic.named_parameters() if n.endswith("bias")][-1]


def test_q_max_is_twice_the_largest_discounted_return():
    assert q_limit(293.728, 0.99) == pytest.approx(58745.6)
    assert q_limit(1.0, 0.5) == pytest.approx(4.0)
    assert CriticWatch(10.0).q_max(0.9) == pytest.approx(200.0)


def test_the_learner_watches_its_critic_against_the_tasks_reward_bound(tmp_path, task):
    assert task.reward_bound == pytest.approx(293.728)  # passage: 220 stated + the action cost 73.7 (was 1,000,073)
    loop = _loop(tmp_path, task)
    assert loop.trainer.watch is not None and loop.trainer.watch.reward_bound == task.reward_bound
    assert loop.trainer.watch.q_max(loop.trainer.algo.model.gamma) == pytest.approx(58745.6)
    bare, _ = open_learner(SMALL, 1, tmp_path / "bare", resume=False, logger_formats=("csv",), task=None)
    assert bare.watch is None and bare.q_rollbacks == 0  # no task: nothing to hold the critic to


@pytest.mark.parametrize("algo", ["tqc", "sac", "sac_ln"])
def test_critic_values_reads_every_critic(tmp_path, task, algo):
    loop = _loop(tmp_path, task, algo)
    model = loop.trainer.algo.model
    q = critic_values(model, np.zeros((5, 5), np.float32), np.zeros((5, 2), np.float32))
    width = model.critic.n_critics * (model.critic.n_quantiles if algo == "tqc" else 1)
    assert q.shape == (5, width) and q.dtype == np.float64 and np.isfinite(q).all()


def test_the_rows_checked_are_evenly_spaced_within_the_iterations_sample_limit(tmp_path, task):
    loop = _loop(tmp_path, task)
    rb = loop.trainer.buffer
    watch = CriticWatch(1.0, rows=4)
    assert watch._rows(rb, None).size == 0  # nothing stored
    _feed(loop, task)  # 32 rows
    assert watch._rows(rb, None).tolist() == [0, 10, 21, 31]
    assert watch._rows(rb, 24).tolist() == [0, 8, 15, 23]
    assert CriticWatch(1.0, rows=256)._rows(rb, None).tolist() == list(range(32))


@pytest.mark.parametrize("algo", ["tqc", "sac", "sac_ln"])
def test_an_iteration_that_takes_q_beyond_q_max_is_rolled_back_exactly(tmp_path, task, algo, monkeypatch, caplog):
    loop = _loop(tmp_path, task, algo)
    _feed(loop, task)
    assert loop.work() and loop.trainer.q_rollbacks == 0  # an ordinary iteration stands
    model = loop.trainer.algo.model
    before = _state(loop.trainer.algo)
    train = model.train

    def diverging(*args, **kwargs):  # an iteration after which every Q is 1e6 (Q_max: 58,746)
        train(*args, **kwargs)
        with torch.no_grad():
            _last_bias(model.critic).fill_(1e6)

    monkeypatch.setattr(model, "train", diverging)
    with caplog.at_level(logging.WARNING, logger="khgrl.learner"):
        assert loop.work()
    tr = loop.trainer
    assert tr.q_rollbacks == 1 and tr.rollbacks == 0 and tr.iterations == 2
    after = _state(tr.algo)
    assert all(torch.equal(before[k], after[k]) for k in before), "not restored to before the iteration"
    assert "rolled back: the critic's |Q| 1e+06" in caplog.text and "> Q_max 5.875e+04" in caplog.text
    assert tr.watch.largest > 9.9e5 and loop.summary()["q_rollbacks"] == 1
    monkeypatch.undo()
    _feed(loop, task, [4])
    assert loop.work() and tr.q_rollbacks == 1  # training goes on from the restored state


def test_rewards_beyond_the_bound_in_the_buffer_are_kept_out_of_the_critic(tmp_path, task):
    """Rewards of 999,000 stored without the check (as the old default bound let an actor with the run's keys
    store them): the critic's Q climbs past Q_max, and each such iteration is rolled back, so the critic the learner
    keeps stays within Q_max. (A reward bound of 0.1, Q_max 20, so that Q gets there within a few iterations at a
    learning rate of 1e-3.)"""
    loop = _loop(tmp_path, task)
    _feed(loop, task)
    assert loop.work()
    tr = loop.trainer
    tr.watch = CriticWatch(0.1)
    tr.buffer.rewards[:32, 0] = 999_000.0
    q_max = tr.watch.q_max(tr.algo.model.gamma)
    for seq in range(4, 40):
        _feed(loop, task, [seq])
        assert loop.work()
        if tr.q_rollbacks:
            break
    assert tr.q_rollbacks >= 1, f"Q never passed Q_max {q_max:g} (largest {tr.watch.largest:g})"
    rb = tr.buffer
    q = critic_values(tr.algo.model, rb.observations[:rb.pos, 0], rb.actions[:rb.pos, 0])
    assert np.abs(q).max() <= q_max and tr.rollbacks == 0


def test_the_check_draws_no_random_numbers_and_is_cheap(tmp_path, task):
    loop = _loop(tmp_path, task)
    _feed(loop, task)
    torch_rng, np_rng = torch.get_rng_state(), np.random.get_state()
    assert loop.trainer.watch.check(loop.trainer.algo, None) is None
    assert torch.equal(torch_rng, torch.get_rng_state()) and np.array_equal(np_rng[1], np.random.get_state()[1])
    assert loop.work()
    s = loop.summary()
    assert s["q_rollbacks"] == 0 and 0 < s["q_largest"] < 100 and s["q_check_ms"] < 1000  # (5 ms in a run)


def test_a_watch_logs_the_first_ten_then_every_hundredth(tmp_path, task, caplog):
    loop = _loop(tmp_path, task)
    _feed(loop, task)
    watch = CriticWatch(dataclasses.replace(task, reward_bound=1e-9).reward_bound)
    with caplog.at_level(logging.WARNING, logger="khgrl.learner"):
        for _ in range(120):
            assert watch.check(loop.trainer.algo, None) is not None
    assert watch.rollbacks == 120 and caplog.text.count("rolled back") == 11
