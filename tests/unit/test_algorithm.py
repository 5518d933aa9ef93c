"""The learner-algorithm interface (learner/algorithm.py) with its default implementation, sb3-contrib TQC:
the registry, the actor's policy taking the learner's weights, checkpoints of one algorithm refused by another."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import RunConfig, TQCSettings
from khgrl.common.tasks.spaces import SpacesEnv
from khgrl.learner import algorithm
from khgrl.learner.algorithm import algorithm_class, check_algorithm
from khgrl.learner.checkpoint import CheckpointError, save_checkpoint
from khgrl.learner.resume import open_learner
from khgrl.learner.tqc import TQCAlgorithm

SMALL = TQCSettings(learning_starts=16, buffer_size=200, net_arch=(16, 16), batch_size=8, gradient_steps=2)


def test_registry_names_the_default_and_refuses_unknown_names():
    assert RunConfig().algo == algorithm.DEFAULT == "tqc" and algorithm_class("tqc") is TQCAlgorithm
    assert check_algorithm("tqc") == "tqc"
    with pytest.raises(ValueError, match="unknown --algo 'ppo': registered are tqc"):
        algorithm_class("ppo")
    with pytest.raises(ValueError, match="algo"):
        RunConfig(algo="no such/name").validate()


def test_actor_policy_takes_the_learners_weights_and_acts_as_the_learners_policy(tmp_path):
    trainer, _ = open_learner(SMALL, 4, tmp_path / "learner", resume=False, logger_formats=("csv",))
    algo = trainer.algo
    rng = np.random.default_rng(0)
    n = 40
    algo.store(rng.random((n, 5), dtype=np.float32), rng.random((n, 5), dtype=np.float32),
               rng.uniform(-1, 1, (n, 2)).astype(np.float32), rng.standard_normal(n).astype(np.float32),
               np.zeros(n, np.float32), np.zeros(n, np.float32), intervened=np.zeros(n, np.uint8),
               clipped=np.zeros(n, np.uint8), actor=0, first_step=0)
    algo.train(2, timestep=24, sample_limit=24)
    assert algo.buffer.sample_limit is None and algo.model.num_timesteps == 24
    weights = algo.policy_weights()
    assert all(v.dtype == np.float32 and isinstance(v, np.ndarray) for v in weights.values())

    env = SpacesEnv()
    torch.manual_seed(1)
    policy = TQCAlgorithm.actor_policy(env.observation_space, env.action_space, SMALL)
    assert policy.weights_template() == {k: v.shape for k, v in weights.items()}
    obs = rng.random(5, dtype=np.float32)
    before, _ = policy.predict(obs, deterministic=True)
    policy.load_weights({k: torch.from_numpy(v) for k, v in weights.items()})
    after, _ = policy.predict(obs, deterministic=True)
    learner_action, _ = algo.model.policy.predict(obs, deterministic=True)
    np.testing.assert_allclose(after, learner_action, rtol=1e-6)
    assert not np.allclose(before, after)


def test_a_checkpoint_is_resumed_only_by_the_algorithm_that_wrote_it(tmp_path, monkeypatch):
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    path = save_checkpoint(tmp_path / "learner", trainer.algo, {**trainer.state(), **streams.state()})
    assert (path / "model.zip").is_file() and (path / "replay_buffer.pkl").is_file()
    again, _ = open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",))
    assert isinstance(again.algo, TQCAlgorithm) and again.state()["algo"] == "tqc"
    monkeypatch.setitem(algorithm.REGISTRY, "other", "khgrl.learner.tqc:TQCAlgorithm")
    with pytest.raises(CheckpointError, match="a checkpoint of a tqc learner; this run's --algo is other"):
        open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",), algo="other")
