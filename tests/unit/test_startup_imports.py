"""A human-input client loads a task without the numerical stack: scikit-learn, scipy's linear algebra, torch and
MuJoCo stay out of its process (they cost about 3 CPU-seconds at every start; the KMP's code imports them when it
fits a model)."""

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
