"""``--algo sac_ln`` (learner/sac_ln.py) without processes: SB3's SAC with HIL-SERL's LayerNorm/tanh networks,
entropy temperature and target entropy; it trains, rolls back, checkpoints and resumes, and an actor's policy of
the same class takes its weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import RunConfig, TQCSettings, resolve
from khgrl.common.tasks.spaces import SpacesEnv
from khgrl.learner.algorithm import MODEL_FILE, algorithm_class
from khgrl.learner.checkpoint import save_checkpoint
from khgrl.learner.resume import open_learner
from khgrl.learner.sac_ln import LayerNormSACPolicy, SACLNAlgorithm
from torch import nn

SMALL = TQCSettings(learning_starts=16, buffer_size=200, net_arch=(16, 16), batch_size=8, gradient_steps=2)
RLPD = TQCSettings(**{**SMALL.__dict__, "sampling": "rlpd"})


def _store(algo, n: int = 40) -> None:
    rng = np.random.default_rng(0)
    algo.store(rng.random((n, 5), dtype=np.float32), rng.random((n, 5), dtype=np.float32),
               rng.uniform(-1, 1, (n, 2)).astype(np.float32), rng.standard_normal(n).astype(np.float32),
               np.zeros(n, np.float32), np.zeros(n, np.float32), intervened=(np.arange(n) % 4 == 0).astype(np.uint8),
               clipped=np.zeros(n, np.uint8), actor=0, first_step=0)


def _layers(net: nn.Module) -> list[type]:
    return [type(m) for m in net]


def test_sac_ln_is_sb3s_sac_with_hil_serls_networks_and_temperature():
    from stable_baselines3 import SAC

    assert algorithm_class("sac_ln") is SACLNAlgorithm
    model = SACLNAlgorithm.build(None, SMALL, 3, "cpu").model
    assert isinstance(model, SAC) and isinstance(model.policy, LayerNormSACPolicy)
    assert (model.learning_rate, model.tau, model.gamma, model.batch_size, model.gradient_steps,
            model.train_freq.frequency, model.buffer_size) == (1e-3, 0.02, 0.99, 8, 2, 8, 200)  # the run's settings
    hidden = [nn.Linear, nn.LayerNorm, nn.Tanh] * 2
    for critic in (model.critic, model.critic_target):
        assert critic.n_critics == 2 and len(critic.q_networks) == 2
        for q in critic.q_networks:
            assert _layers(q) == [*hidden, nn.Linear] and q[-1].out_features == 1
    assert _layers(model.actor.latent_pi) == hidden
    assert model.target_entropy == -1.0  # -|A| / 2, |A| = 2
    assert model.log_ent_coef.exp().item() == pytest.approx(0.01)
    again = SACLNAlgorithm.build(None, SMALL, 3, "cpu").model.policy.state_dict()
    assert all(torch.equal(v, again[k]) for k, v in model.policy.state_dict().items())  # seeded
    assert model.replay_buffer.prior_fraction == 0.0 and model.replay_buffer_kwargs == {}
    assert SACLNAlgorithm.build(None, RLPD, 3, "cpu").buffer.prior_fraction == 0.5


def test_hil_serl_method_implies_sac_ln_with_rlpd_sampling():
    cfg = resolve(overrides={"method": "hil-serl"})  # (validated: sac_ln is registered)
    assert (cfg.algo, cfg.tqc.sampling) == ("sac_ln", "rlpd") and RunConfig().algo == "tqc"


def test_sac_ln_trains_rolls_back_and_its_weights_reach_an_actor_policy(tmp_path):
    algo = SACLNAlgorithm.build(None, RLPD, 1, "cpu")
    algo.set_logger(tmp_path, ("csv",))
    _store(algo)
    before = {k: v.clone() for k, v in algo.model.policy.state_dict().items()}
    snap = algo.snapshot()
    algo.train(2, timestep=24, sample_limit=24)
    assert algo.fault() is None and algo.buffer.sampled_prior == 8  # 2 steps x 4 of 8 from the intervened slots
    after = algo.model.policy.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("critic."))
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("actor."))
    trained = {k: v.clone() for k, v in after.items()}
    algo.restore(snap)
    assert all(torch.equal(before[k], v) for k, v in algo.model.policy.state_dict().items())
    algo.model.policy.load_state_dict(trained)

    weights = algo.policy_weights()
    assert any("latent_pi.1." in k for k in weights)  # the actor's LayerNorm travels with it
    env = SpacesEnv()
    policy = SACLNAlgorithm.actor_policy(env.observation_space, env.action_space, SMALL)
    assert isinstance(policy.policy, LayerNormSACPolicy)
    assert policy.weights_template() == {k: v.shape for k, v in weights.items()}
    policy.load_weights({k: torch.from_numpy(v) for k, v in weights.items()})
    obs = np.full(5, 0.3, np.float32)
    np.testing.assert_allclose(policy.predict(obs, deterministic=True)[0],
                               algo.model.policy.predict(obs, deterministic=True)[0], rtol=1e-6)


def test_a_sac_ln_checkpoint_resumes_and_its_model_file_loads_as_a_policy(tmp_path):
    trainer, streams = open_learner(RLPD, 1, tmp_path / "learner", resume=False, logger_formats=("csv",),
                                    algo="sac_ln")
    _store(trainer.algo)
    trainer.algo.train(2, timestep=24, sample_limit=24)
    weights = trainer.algo.policy_weights()
    path = save_checkpoint(tmp_path / "learner", trainer.algo, {**trainer.state(), **streams.state()})
    again, _ = open_learner(RLPD, 1, tmp_path / "learner", resume=True, logger_formats=("csv",), algo="sac_ln")
    model = again.algo.model
    assert isinstance(again.algo, SACLNAlgorithm) and isinstance(model.policy, LayerNormSACPolicy)
    assert again.buffer.pos == 40 and again.buffer.prior_fraction == 0.5 and again.buffer.sampled_prior == 8
    assert model.target_entropy == -1.0 and again.algo.fault() is None
    for k, v in weights.items():
        np.testing.assert_array_equal(again.algo.policy_weights()[k], v)
    again.algo.train(2, timestep=32, sample_limit=32)  # training goes on (optimisers restored)
    assert again.algo.fault() is None and again.buffer.sampled_prior == 16

    env = SpacesEnv()
    policy = SACLNAlgorithm.checkpoint_policy(path / MODEL_FILE, env.observation_space, env.action_space, SMALL)
    obs = np.full(5, 0.3, np.float32)
    np.testing.assert_allclose(policy.predict(obs, deterministic=True)[0],
                               trainer.algo.model.policy.predict(obs, deterministic=True)[0], rtol=1e-6)
    with pytest.raises(ValueError, match="does not fit"):
        SACLNAlgorithm.checkpoint_policy(path / MODEL_FILE, env.observation_space, env.action_space,
                                         TQCSettings(net_arch=(32, 32)))
