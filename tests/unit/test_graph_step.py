"""The learner's gradient-step function (learner/step.py, what a CUDA graph captures) is the library's algorithm:
from the same minibatches and the same noise, 50 steps of it leave the same parameters, optimiser states and
entropy coefficient as SB3's / sb3-contrib's own ``train()`` -- for TQC, SAC and SAC-LN (HIL-SERL's SAC, whose
reference step is SB3's ``SAC.train`` with its LayerNorm policy), in float64 on the CPU. Also: the step's minibatch
rows (``StreamReplayBuffer.sample_into``) are the numbers ``sample`` gives, from the same random draws; and the
CUDA-graph learner's bookkeeping, run eagerly on the CPU (learner/cuda_graph.py), trains as ``train()`` does."""

from __future__ import annotations

from types import SimpleNamespace
from unittest import mock

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import TQCSettings
from khgrl.learner.algorithm import algorithm_class
from khgrl.learner.step import Minibatch, SB3Step
from stable_baselines3.common.type_aliases import ReplayBufferSamples

OBS, ACT, BATCH, STEPS = 6, 2, 32, 50


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread (the learner's; also the fastest for these small networks on a shared machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
SETTINGS = TQCSettings(learning_starts=0, net_arch=(32, 32), batch_size=BATCH, buffer_size=500)
TASK = SimpleNamespace(out_dim=ACT, obs_low=[-5.0] * OBS, obs_high=[5.0] * OBS)


def _model(algo: str, seed: int = 5):
    """The learner's model of ``algo`` in float64 (networks and entropy coefficient)."""
    from stable_baselines3.common.logger import Logger

    model = algorithm_class(algo).build(TASK, SETTINGS, seed, "cpu").model
    model.set_logger(Logger(folder=None, output_formats=[]))  # (configure(None) leaves a directory in /tmp)
    model.policy.double()
    model.log_ent_coef.data = model.log_ent_coef.data.double()
    return model


def _batches(seed: int = 11) -> list[ReplayBufferSamples]:
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(STEPS):
        obs, nxt = torch.randn(BATCH, OBS, generator=g, dtype=torch.float64), torch.randn(
            BATCH, OBS, generator=g, dtype=torch.float64)
        act = torch.rand(BATCH, ACT, generator=g, dtype=torch.float64) * 2 - 1
        done = (torch.rand(BATCH, 1, generator=g) < 0.1).double()
        out.append(ReplayBufferSamples(obs, act, nxt, done, torch.randn(BATCH, 1, generator=g, dtype=torch.float64)))
    return out


def _state(model) -> dict[str, torch.Tensor]:
    """Everything a step changes: networks, target networks, entropy coefficient, the optimisers' moments."""
    out = {f"policy.{k}": v for k, v in model.policy.state_dict().items()}
    out["log_ent_coef"] = model.log_ent_coef.detach()
    for name in ("actor", "critic"):
        opt = getattr(model, name).optimizer
        for i, p in enumerate(opt.param_groups[0]["params"]):
            out[f"{name}.exp_avg.{i}"] = opt.state[p]["exp_avg"]
            out[f"{name}.exp_avg_sq.{i}"] = opt.state[p]["exp_avg_sq"]
    return out


@pytest.mark.parametrize("algo", ["tqc", "sac", "sac_ln"])
def test_step_function_leaves_the_libraries_parameters(algo):
    """Fails when the step function departs from the library's step (checked by taking the entropy coefficient
    after its Adam step instead of before, as SB3 does: parameters apart by 4e-3 after 50 steps)."""
    batches = _batches()
    identity = mock.patch("stable_baselines3.common.policies.preprocess_obs", lambda obs, *a, **k: obs)
    with identity:  # (SB3 casts Box observations to float32; float64 throughout here, on both sides)
        theirs = _model(algo)
        it = iter(batches)
        theirs.replay_buffer.sample = lambda *a, **k: next(it)
        torch.manual_seed(123)
        theirs.train(gradient_steps=STEPS, batch_size=BATCH)

        ours = _model(algo)
        step = SB3Step(ours)
        torch.manual_seed(123)
        scalars = torch.stack([step(Minibatch(*b[:5]), polyak=k % ours.target_update_interval == 0)
                               for k, b in enumerate(batches)])
    a, b = _state(theirs), _state(ours)
    assert a.keys() == b.keys()
    worst = max((a[k] - b[k]).abs().max().item() for k in a)
    assert worst <= 1e-8, worst
    fresh = _model(algo).policy.state_dict()
    moved = max((a[f"policy.{k}"] - v).abs().max().item() for k, v in fresh.items())
    assert moved > 1e-3  # (the steps did train)
    logged = theirs.logger.name_to_value
    mean = scalars.mean(dim=0)
    assert abs(mean[1].item() - logged["train/actor_loss"]) <= 1e-8
    assert abs(mean[2].item() - logged["train/critic_loss"]) <= 1e-8
    assert abs(mean[3].item() - logged["train/ent_coef_loss"]) <= 1e-8


def test_sample_into_gives_samples_numbers_from_the_same_draws():
    """``sample_into`` writes what ``sample`` returns and leaves numpy's generator where ``sample`` does, for
    uniform and RLPD sampling and within a ``sample_limit``."""
    for fraction in (0.0, 0.5):
        algo = algorithm_class("tqc").build(TASK, SETTINGS, 1, "cpu")
        rb = algo.buffer
        rb.prior_fraction = fraction
        rng = np.random.default_rng(0)
        n = 300
        algo.store(rng.normal(size=(n, OBS)).astype(np.float32), rng.normal(size=(n, OBS)).astype(np.float32),
                   rng.uniform(-1, 1, (n, ACT)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                   (rng.random(n) < 0.1).astype(np.float32), (rng.random(n) < 0.5).astype(np.float32),
                   intervened=(rng.random(n) < 0.2).astype(np.uint8), clipped=np.zeros(n, np.uint8), actor=0,
                   first_step=0)
        for limit in (None, 120):
            rb.sample_limit = limit
            np.random.seed(4)
            s = rb.sample(BATCH)
            after = np.random.random()
            rows = np.empty((BATCH, rb.minibatch_width()), np.float32)
            np.random.seed(4)
            rb.sample_into(rows)
            assert np.random.random() == after
            got = Minibatch.split(torch.from_numpy(rows), OBS, ACT)
            for x, y in zip(got, s[:5]):
                assert torch.equal(x, y)


def _filled(algo: str, cuda_graph_trainer: bool):
    """The learner's ``algo`` (float32, CPU) with 300 stored transitions; with ``cuda_graph_trainer``, trained by
    the CUDA-graph learner's iteration run eagerly."""
    from khgrl.learner.cuda_graph import GraphedTrainer
    from stable_baselines3.common.logger import Logger

    algo_ = algorithm_class(algo).build(TASK, SETTINGS, 5, "cpu")
    algo_.model.set_logger(Logger(folder=None, output_formats=[]))  # (configure(None) leaves a directory in /tmp)
    rng = np.random.default_rng(0)
    n = 300
    algo_.store(rng.normal(size=(n, OBS)).astype(np.float32), rng.normal(size=(n, OBS)).astype(np.float32),
                rng.uniform(-1, 1, (n, ACT)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                (rng.random(n) < 0.1).astype(np.float32), np.zeros(n, np.float32),
                intervened=np.zeros(n, np.uint8), clipped=np.zeros(n, np.uint8), actor=0, first_step=0)
    if cuda_graph_trainer:
        algo_.graphed = GraphedTrainer(algo_.model, graph=False)
    return algo_


@pytest.mark.parametrize("algo", ["tqc", "sac_ln"])
def test_graph_learners_iteration_trains_as_train_does(algo):
    """The CUDA-graph learner's iteration (minibatches drawn as rows, the scalars kept until the iteration ends),
    eager on the CPU: the same minibatches, parameters and logged losses as SB3's ``train()`` through the learner's
    interface (float32: within rounding), within a ``sample_limit``; and its in-place snapshot restores exactly.
    Fails when the rows are drawn otherwise than ``sample`` draws them (checked by making ``sample_into`` ignore
    the ``sample_limit``: parameters apart by more than 1e-3)."""
    theirs, ours = _filled(algo, False), _filled(algo, True)
    for a in (theirs, ours):
        np.random.seed(2)
        torch.manual_seed(2)
        for it in range(3):
            a.train(8, timestep=200 + 8 * it, sample_limit=200 + 8 * it)
    a, b = theirs.model.policy.state_dict(), ours.model.policy.state_dict()
    assert max((a[k] - b[k]).abs().max().item() for k in a) < 1e-5
    la, lb = theirs.model.logger.name_to_value, ours.model.logger.name_to_value
    for key in ("train/actor_loss", "train/critic_loss", "train/ent_coef_loss", "train/ent_coef"):
        assert abs(la[key] - lb[key]) <= 1e-5 * max(1.0, abs(la[key])), key
    assert ours.model._n_updates == theirs.model._n_updates == 24
    before = {k: v.clone() for k, v in b.items()}
    snap = ours.snapshot()
    assert snap.get("graphed")  # (preallocated, in place)
    ours.train(8, timestep=300, sample_limit=None)
    assert any(not torch.equal(before[k], v) for k, v in ours.model.policy.state_dict().items())
    ours.restore(snap)
    assert all(torch.equal(before[k], v) for k, v in ours.model.policy.state_dict().items())
    assert ours.model._n_updates == 24 and ours.fault() is None


def test_compiled_loss_trains_within_rounding_of_train():
    """``--compile-loss`` (the CPU, opt-in): TQC's quantile Huber loss compiled by torch.compile; an iteration leaves
    the parameters SB3's ``train()`` leaves to within float32 rounding (it does not round the same: opt-in). Fails
    if the compiled loss is not the library's (or not used: the model trains with SB3's own function then)."""
    from sb3_contrib.common.utils import quantile_huber_loss

    settings = TQCSettings(learning_starts=0, net_arch=(32, 32), batch_size=BATCH, buffer_size=500, compile_loss=True)
    theirs = _filled("tqc", False)
    ours = algorithm_class("tqc").build(TASK, settings, 5, "cpu")
    ours.model.set_logger(theirs.model.logger)
    theirs_rb, ours_rb = theirs.buffer, ours.buffer
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        getattr(ours_rb, name)[:] = getattr(theirs_rb, name)
    ours_rb.pos, ours_rb.full = theirs_rb.pos, theirs_rb.full
    assert ours.graphed is not None and ours.graphed.step.huber is not quantile_huber_loss
    for a in (theirs, ours):
        np.random.seed(2)
        torch.manual_seed(2)
        a.train(8, timestep=300, sample_limit=None)
    a, b = theirs.model.policy.state_dict(), ours.model.policy.state_dict()
    worst = max((a[k] - b[k]).abs().max().item() for k in a)
    assert 0 <= worst < 1e-4, worst
