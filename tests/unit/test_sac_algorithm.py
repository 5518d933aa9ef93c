"""``--algo sac`` (learner/sac.py) without processes: SB3's SAC with the run's settings, seeded as SB3's own,
its policy weights taken by an actor's SAC policy, a checkpoint resumed by it (and refused by TQC)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import TQCSettings
from khgrl.common.tasks.spaces import SpacesEnv
from khgrl.learner.algorithm import algorithm_class
from khgrl.learner.checkpoint import CheckpointError, save_checkpoint
from khgrl.learner.replay import StreamReplayBuffer
from khgrl.learner.resume import open_learner
from khgrl.learner.sac import SACAlgorithm

SMALL = TQCSettings(learning_starts=16, buffer_size=200, net_arch=(16, 16), batch_size=8, gradient_steps=2)


def _store(algo, n: int = 40) -> None:
    rng = np.random.default_rng(0)
    algo.store(rng.random((n, 5), dtype=np.float32), rng.random((n, 5), dtype=np.float32),
               rng.uniform(-1, 1, (n, 2)).astype(np.float32), rng.standard_normal(n).astype(np.float32),
               np.zeros(n, np.float32), np.zeros(n, np.float32), intervened=np.zeros(n, np.uint8),
               clipped=np.zeros(n, np.uint8), actor=0, first_step=0)


def test_sac_is_sb3s_sac_with_the_runs_settings():
    from stable_baselines3 import SAC

    assert algorithm_class("sac") is SACAlgorithm
    ours = SACAlgorithm.build(None, SMALL, 3, "cpu").model
    plain = SAC("MlpPolicy", SpacesEnv(), **{**SMALL.sb3_kwargs(3), "device": "cpu"})
    assert isinstance(ours, SAC) and isinstance(ours.replay_buffer, StreamReplayBuffer)
    assert (ours.learning_rate, ours.tau, ours.gamma, ours.batch_size, ours.gradient_steps, ours.buffer_size) == \
        (1e-3, 0.02, 0.99, 8, 2, 200)
    a, b = ours.policy.state_dict(), plain.policy.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)  # seeded as SB3's own


def test_sac_weights_reach_an_actor_policy_and_a_checkpoint_resumes(tmp_path):
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",), algo="sac")
    _store(trainer.algo)
    trainer.algo.train(2, timestep=24, sample_limit=24)
    weights = trainer.algo.policy_weights()
    env = SpacesEnv()
    policy = SACAlgorithm.actor_policy(env.observation_space, env.action_space, SMALL)
    assert policy.weights_template() == {k: v.shape for k, v in weights.items()}
    policy.load_weights({k: torch.from_numpy(v) for k, v in weights.items()})
    obs = np.full(5, 0.3, np.float32)
    np.testing.assert_allclose(policy.predict(obs, deterministic=True)[0],
                               trainer.algo.model.policy.predict(obs, deterministic=True)[0], rtol=1e-6)

    save_checkpoint(tmp_path / "learner", trainer.algo, {**trainer.state(), **streams.state()})
    again, _ = open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",), algo="sac")
    assert isinstance(again.algo, SACAlgorithm) and again.buffer.pos == 40
    np.testing.assert_array_equal(again.algo.policy_weights()["mu.weight"], weights["mu.weight"])
    with pytest.raises(CheckpointError, match="a checkpoint of a sac learner; this run's --algo is tqc"):
        open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",))
