"""``--recipe hil-serl`` without processes: HIL-SERL's update schedule (learner/sac_cta.py), its preset
(common/config/hilserl.py), the teacher's successful demonstrations (actor/teach.py), the finishing takeover and
the task-sized safety box."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import TQCSettings
from khgrl.learner.algorithm import algorithm_class
from khgrl.learner.sac_cta import CTASAC, SACCTAAlgorithm
from khgrl.learner.sac_ln import SACLNAlgorithm

SMALL = TQCSettings(learning_starts=16, buffer_size=200, net_arch=(16, 16), batch_size=8, gradient_steps=2)


def _store(algo, n: int = 40) -> None:
    rng = np.random.default_rng(0)
    algo.store(rng.random((n, 5), dtype=np.float32), rng.random((n, 5), dtype=np.float32),
               rng.uniform(-1, 1, (n, 2)).astype(np.float32), rng.standard_normal(n).astype(np.float32),
               np.zeros(n, np.float32), np.zeros(n, np.float32), intervened=(np.arange(n) % 4 == 0).astype(np.uint8),
               clipped=np.zeros(n, np.uint8), actor=0, first_step=0)


def _trained(cls, settings: TQCSettings, tmp_path) -> dict[str, torch.Tensor]:
    algo = cls.build(None, settings, 5, "cpu")
    algo.set_logger(tmp_path, ("csv",))
    _store(algo)
    algo.train(3, timestep=24, sample_limit=None)
    assert algo.fault() is None
    return algo.model.policy.state_dict()


def test_sac_cta_with_ratio_1_and_backup_entropy_is_sb3s_sac_step_for_step(tmp_path):
    """With cta_ratio 1 and the entropy backup on, sac_cta's step is SB3's SAC.train: the same parameters after 3
    steps as sac_ln's (SB3's own train()), so the replaced train() keeps SAC's order and random draws."""
    assert algorithm_class("sac_cta") is SACCTAAlgorithm
    ours, sb3 = _trained(SACCTAAlgorithm, SMALL, tmp_path / "a"), _trained(SACLNAlgorithm, SMALL, tmp_path / "b")
    assert all(torch.equal(v, sb3[k]) for k, v in ours.items())


def test_sac_cta_updates_the_critics_cta_ratio_times_per_actor_update(tmp_path):
    """cta_ratio 2: per gradient step two critic updates (two minibatches drawn, two target Polyak steps) and one
    actor and temperature update; without the entropy backup the critics learn otherwise than with it."""
    hs = TQCSettings(**{**SMALL.__dict__, "cta_ratio": 2, "backup_entropy": False})
    algo = SACCTAAlgorithm.build(None, hs, 5, "cpu")
    model = algo.model
    assert isinstance(model, CTASAC) and (model.cta_ratio, model.backup_entropy) == (2, False)
    assert not SACCTAAlgorithm.graphs_on(TQCSettings(device="cuda"), "cuda")
    algo.set_logger(tmp_path, ("csv",))
    _store(algo)
    draws, steps = [], {"critic": 0, "actor": 0}
    sample = model.replay_buffer.sample
    model.replay_buffer.sample = lambda *a, **k: draws.append(1) or sample(*a, **k)
    for name in steps:
        opt = getattr(model, name).optimizer
        opt.register_step_post_hook(lambda *_, n=name: steps.__setitem__(n, steps[n] + 1))
    algo.train(3, timestep=24, sample_limit=None)
    assert (len(draws), steps["critic"], steps["actor"]) == (6, 6, 3) and model._n_updates == 3
    assert algo.fault() is None
    on = _trained(SACCTAAlgorithm, TQCSettings(**{**hs.__dict__, "backup_entropy": True}), tmp_path / "c")
    off = _trained(SACCTAAlgorithm, hs, tmp_path / "d")
    assert any(not torch.equal(v, on[k]) for k, v in off.items() if k.startswith("critic."))


def test_cta_ratio_must_be_positive():
    with pytest.raises(ValueError, match="cta_ratio"):
        TQCSettings(cta_ratio=0).validate()


def test_the_recipe_presets_hil_serls_published_settings_unless_given():
    """--recipe hil-serl implies --method hil-serl and HIL-SERL's settings (lr 3e-4, tau 0.005, discount 0.97,
    cta_ratio 2, no backup entropy, 20 demonstrations, the finishing takeover, the task box); a flag given wins;
    the default recipe changes nothing."""
    from khgrl.common.config.hilserl import recipe_runtime
    from khgrl.common.config.settings import RunConfig, resolve

    cfg = resolve(overrides={"recipe": "hil-serl"})
    t = cfg.tqc
    assert (cfg.method, cfg.algo, cfg.takeover) == ("hil-serl", "sac_cta", "finish")
    assert (t.learning_rate, t.tau, t.gamma, t.cta_ratio, t.backup_entropy, t.batch_size, t.sampling) == \
        (3e-4, 0.005, 0.97, 2, False, 256, "rlpd")
    assert (cfg.hilserl.teacher_demos, cfg.hilserl.tries, cfg.hilserl.safety_box) == (20, 60, "task")
    assert resolve(overrides={"recipe": "hil-serl", "tqc": {"gamma": 0.99}}).tqc.gamma == 0.99
    assert resolve(overrides={"method": "hil-serl"}).tqc == resolve(overrides={"method": "hil-serl",
                                                                               "recipe": "none"}).tqc
    assert RunConfig().tqc.cta_ratio == 1 and RunConfig().tqc.backup_entropy and RunConfig().recipe == "none"
    with pytest.raises(ValueError, match="option of method hil-serl"):
        resolve(overrides={"recipe": "hil-serl", "method": "khgrl"})
    cited = recipe_runtime(cfg)["recipe"]
    assert cited["source"].startswith("rail-berkeley/hil-serl@5d02aed")
    assert cited["settings"]["tqc.gamma"] == {"value": 0.97, "source": "examples/experiments/config.py:11, "
                                              "serl_launcher/serl_launcher/utils/launcher.py:84"}
    assert recipe_runtime(RunConfig()) == {}
