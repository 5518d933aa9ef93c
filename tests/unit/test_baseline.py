"""A short real run of the single-process baseline (learner/baseline.py): SB3 TQC on the passage world with
the scripted human, whose interventions reach the replay buffer as the human's actions."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from khgrl.common.config.settings import TQCSettings
from khgrl.learner.baseline import InterventionTQC, ReferenceConfig, build_env, run_reference

EPISODES = 2  # episode 1: no human (blocked at the second wall); episode 2: the scripted human


@pytest.fixture(scope="module")
def ref_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("reference")
    # the tests' small networks, on seed 1 (seed 0's small policy fails before the human's window in episode 2)
    config = ReferenceConfig(scenario="low_cov", method="khgrl", episodes=EPISODES, human_episodes=(2,), seed=1,
                             tqc=TQCSettings(net_arch=(64, 64), batch_size=64))
    episodes = run_reference(config, run_dir, progress=False)
    return run_dir, episodes


@pytest.mark.slow
def test_reference_files(ref_run):
    run_dir, _ = ref_run
    for name in ("config.json", "episodes.csv", "episodes.json", "summary.json"):
        assert (run_dir / name).is_file(), name
    config = json.loads((run_dir / "config.json").read_text())
    assert config["reference"]["scenario"] == "low_cov"
    assert config["reference"]["method"] == "khgrl"
    assert config["reference"]["episodes"] == EPISODES
    assert config["tqc"]["gradient_steps"] == "8" and config["tqc"]["train_freq"] == "8"
    with open(run_dir / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["episode"]) for r in rows] == list(range(1, EPISODES + 1))
    assert len(json.loads((run_dir / "episodes.json").read_text())) == EPISODES


@pytest.mark.slow
def test_reference_episodes_and_interventions(ref_run):
    run_dir, episodes = ref_run
    assert [e.episode for e in episodes] == list(range(1, EPISODES + 1))
    first, second = episodes[0], episodes[1]
    assert first.intervention_steps == 0 and first.interventions == 0
    assert second.intervention_steps > 0 and second.interventions == 1
    assert second.mean_abs_xi_h > 0
    # low_cov learns L from the intervention: the scale in force grows beyond L0 = 15
    assert max(second.scale_max) > 15.0 and first.scale_max == [15.0, 15.0]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["intervened_transitions_stored"] == second.intervention_steps > 0
    assert summary["env_steps"] == sum(e.steps for e in episodes)
    # one iteration of 8 gradient steps per 8 environment steps past learning_starts (SB3's learn())
    # (the rollout cut short by the episode limit does not train)
    assert summary["gradient_steps"] == 8 * ((summary["env_steps"] - 1) // 8 - 100 // 8) > 0
    assert summary["final_scale_table_max"][1] > 15.0
    table = np.load(run_dir / "scale_table.npy")
    assert table.shape == (400, 2) and np.all(table >= 1.0)
    for e in episodes:
        assert e.steps > 0 and np.isfinite(e.ret)
        assert e.success or e.failure or e.steps == 400


@pytest.mark.slow
def test_reference_csv_matches_stats(ref_run):
    run_dir, episodes = ref_run
    with open(run_dir / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    for row, e in zip(rows, episodes):
        assert int(row["steps"]) == e.steps
        assert float(row["ret"]) == pytest.approx(e.ret)
        assert int(row["intervention_steps"]) == e.intervention_steps


def test_reference_config_validation():
    with pytest.raises(ValueError):
        ReferenceConfig(method="sac")
    with pytest.raises(ValueError):
        ReferenceConfig(episodes=0)
    with pytest.raises(ValueError):
        ReferenceConfig(tqc=TQCSettings(train_freq=0))


def test_tqc_settings_are_the_papers():
    """The baseline takes its TQC settings from khgrl.common.config.settings.TQCSettings, as the learner does."""
    assert ReferenceConfig().tqc == TQCSettings()
    kw = ReferenceConfig(seed=3).tqc.sb3_kwargs(3)
    assert kw["learning_rate"] == 1e-3 and kw["tau"] == 0.02 and kw["gamma"] == 0.99
    assert kw["train_freq"] == 8 and kw["gradient_steps"] == 8 and kw["ent_coef"] == "auto"
    assert kw["policy_kwargs"] == {"net_arch": [256, 256]} and kw["seed"] == 3
    assert kw["learning_starts"] == 100 and kw["batch_size"] == 256


def test_intervention_tqc_stores_the_human_action():
    """Unit check of the replay-buffer override, without training: intervened transitions get info["action"]."""
    from stable_baselines3.common.buffers import ReplayBuffer

    base, env = build_env(ReferenceConfig(scenario="low_cov", method="kgrl", episodes=1))
    model = InterventionTQC("MlpPolicy", env, **{**TQCSettings().sb3_kwargs(0), "learning_starts": 10**9})
    model.n_intervened_stored = 0
    buf = model.replay_buffer
    assert isinstance(buf, ReplayBuffer)
    obs, _ = env.reset(seed=0)
    model._last_obs = obs[None]
    model._last_original_obs = obs[None]
    new_obs = obs[None]
    human = np.array([[0.25, -0.75]], dtype=np.float32)
    model._store_transition(
        buf, np.array([[0.9, 0.9]], dtype=np.float32), new_obs, np.array([0.0]), np.array([False]),
        [{"intervened": True, "action": human[0]}],
    )
    model._store_transition(
        buf, np.array([[0.1, 0.2]], dtype=np.float32), new_obs, np.array([0.0]), np.array([False]),
        [{"intervened": False, "action": np.zeros(2, dtype=np.float32)}],
    )
    assert model.n_intervened_stored == 1
    np.testing.assert_allclose(buf.actions[0, 0], human[0])
    np.testing.assert_allclose(buf.actions[1, 0], [0.1, 0.2], rtol=1e-6)
