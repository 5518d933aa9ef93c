"""A human-input client loads a task without the numerical stack: scikit-learn, scipy's linear algebra, torch and
MuJoCo stay out of its process (they cost about 3 CPU-seconds at every start; the KMP's code imports them when it
fits a model); an actor's policy is built without the optimizer that would import torch._dynamo."""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import sys
import khgrl.human_bridge.main
from khgrl.common.tasks.api import load_task
load_task(sys.argv[1])
print(' '.join(m for m in ('sklearn', 'scipy.linalg', 'torch', 'mujoco') if m in sys.modules) or 'none')
"""


@pytest.mark.parametrize("spec", ["passage:low_cov", "fetch:moved", "panda:pick"])
def test_a_human_client_loads_a_task_without_the_numerical_stack(spec: str) -> None:
    out = subprocess.run([sys.executable, "-c", PROBE, spec], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["none"], f"{spec}: imported {out.stdout.strip()}"


def test_fitting_a_model_still_imports_what_it_needs(tmp_path, monkeypatch) -> None:
    from khgrl.common.kmp.fit import KMPConfig, fit_model

    monkeypatch.setenv("KHGRL_CACHE_DIR", str(tmp_path))  # (an empty cache: the fit runs)
    from khgrl.common.tasks.passage.task import make_task

    model, ref = fit_model(make_task("low_cov").demos, KMPConfig())
    assert ref.mu.shape[0] == model.n_points and "sklearn" in sys.modules


ACTOR_PROBE = """
import sys
from khgrl.common.config.settings import TQCSettings
from khgrl.common.tasks.spaces import SpacesEnv
from khgrl.learner.algorithm import algorithm_class
env = SpacesEnv()
for name in ('tqc', 'sac', 'sac_ln'):
    policy = algorithm_class(name).actor_policy(env.observation_space, env.action_space, TQCSettings())
    policy.predict(env.observation_space.sample(), deterministic=True)
print('torch._dynamo' in sys.modules)
"""


def test_an_actors_policy_is_built_without_an_optimizer() -> None:
    """An actor's (and an evaluation's) policy gets :class:`Untrained` through SB3's ``optimizer_class`` hook: torch's
    first real optimizer would import ``torch._dynamo`` (about 4 CPU-s at every actor's start), and nothing trains
    there."""
    from khgrl.common.config.settings import TQCSettings
    from khgrl.common.tasks.spaces import SpacesEnv
    from khgrl.learner.algorithm import algorithm_class
    from khgrl.learner.sb3_actor import Untrained

    out = subprocess.run([sys.executable, "-c", ACTOR_PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.split() == ["False"], out.stdout + out.stderr
    env = SpacesEnv()
    policy = algorithm_class("tqc").actor_policy(env.observation_space, env.action_space, TQCSettings())
    assert isinstance(policy.policy.actor.optimizer, Untrained) and policy.policy.actor.optimizer.state_dict() == {}
    with pytest.raises(RuntimeError, match="not trained"):
        policy.policy.critic.optimizer.step()
