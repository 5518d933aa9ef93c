"""The cache of fitted GMMs: a hit gives exactly the fit (so seeded runs are unchanged), any input changed is a
miss, a damaged file is ignored and replaced, and ``KHGRL_CACHE_DIR=off`` turns it off."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from khgrl.common.kmp import gmm_cache
from khgrl.common.kmp.gmr import fit_gmm, reference_distribution


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("KHGRL_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _demos(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 30)
    return np.stack([np.stack([np.sin(3 * t), t ** 2], 1) + 0.01 * rng.standard_normal((30, 2)) for _ in range(5)])


def test_a_hit_is_exactly_the_fit(cache) -> None:
    first = fit_gmm(_demos(), 4, seed=1)
    assert type(first).__name__ == "GaussianMixture" and len(list(cache.glob("gmm-*.npz"))) == 1
    again = fit_gmm(_demos(), 4, seed=1)
    assert isinstance(again, gmm_cache.FittedGMM)
    for name in ("weights_", "means_", "covariances_"):
        assert np.array_equal(getattr(first, name), getattr(again, name))
    a = reference_distribution(_demos(), n_components=4, seed=1)
    b = reference_distribution(_demos(), n_components=4, seed=1)
    assert np.array_equal(a.mu, b.mu) and np.array_equal(a.sigma, b.sigma)


def test_any_input_changed_is_a_miss(cache) -> None:
    fit_gmm(_demos(), 4, seed=1)
    fit_gmm(_demos(), 4, seed=2)
    fit_gmm(_demos(), 3, seed=1)
    fit_gmm(_demos(1), 4, seed=1)
    fit_gmm(_demos(), 4, seed=1, reg_covar=1e-5)
    assert len(list(cache.glob("gmm-*.npz"))) == 5


def test_a_damaged_file_is_ignored_and_replaced(cache) -> None:
    fit_gmm(_demos(), 4, seed=1)
    (path,) = cache.glob("gmm-*.npz")
    path.write_bytes(b"not an npz")
    assert type(fit_gmm(_demos(), 4, seed=1)).__name__ == "GaussianMixture"  # fitted again
    np.savez(path, weights=np.ones(2), means=np.zeros((2, 3)), covariances=np.zeros((2, 3, 3)))  # wrong shapes
    assert type(fit_gmm(_demos(), 4, seed=1)).__name__ == "GaussianMixture"
    assert isinstance(fit_gmm(_demos(), 4, seed=1), gmm_cache.FittedGMM)  # replaced by the fit


def test_off_writes_nothing(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("KHGRL_CACHE_DIR", "off")
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert gmm_cache.cache_dir() is None
    assert type(fit_gmm(_demos(), 4, seed=1)).__name__ == "GaussianMixture"
    assert not list(tmp_path.rglob("gmm-*"))


def test_a_cached_world_is_built_without_scikit_learn(cache) -> None:
    probe = ("import sys; from khgrl.common.tasks.api import load_task; from khgrl.common.tasks.world import "
             "build_task_world; build_task_world(load_task('passage:low_cov')); print('sklearn' in sys.modules)")
    env = {"KHGRL_CACHE_DIR": str(cache), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"}
    runs = [subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=120)
            for _ in range(2)]
    assert [r.stdout.split()[-1] for r in runs] == ["True", "False"], [r.stderr[-500:] for r in runs]
