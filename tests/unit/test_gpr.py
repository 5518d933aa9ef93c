"""The scale's GPR is scikit-learn's Gaussian-process mean to the last bit (seeded runs unchanged), without
scikit-learn in the actor."""

import subprocess
import sys

import numpy as np
import pytest
from khgrl.common.kmp.gpr import GPR
from khgrl.common.kmp.scale import ScaleConfig, ScaleModel
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, WhiteKernel


def _sklearn_means(x, y, q, signal_var, length_scale, noise_var):
    kernel = signal_var * RBF(length_scale=length_scale, length_scale_bounds="fixed") + WhiteKernel(
        noise_var, noise_level_bounds="fixed")
    out = []
    for d in range(y.shape[1]):
        gp = GaussianProcessRegressor(kernel=kernel, optimizer=None, normalize_y=False, alpha=1e-10)
        out.append(gp.fit(x, y[:, d]).predict(q))
    return np.stack(out, axis=1)


@pytest.mark.parametrize("n,d,m", [(1, 1, 1), (7, 1, 3), (120, 1, 2), (60, 2, 3), (400, 1, 1)])
def test_gpr_means_equal_scikit_learns_bit_for_bit(n, d, m):
    rng = np.random.default_rng(n * 10 + d)
    x = rng.uniform(0, 1, (n, d))
    x[n // 2:] = x[: n - n // 2]  # repeated inputs: K is singular without the noise term
    y = rng.normal(0, 1.5, (n, m))
    q = np.concatenate([rng.uniform(-0.2, 1.2, (50, d)), x[:5]])
    ours = GPR(4.0, 0.04, 0.05).fit(x, y).predict(q)
    assert ours.shape == (q.shape[0], m)
    np.testing.assert_array_equal(ours, _sklearn_means(x, y, q, 4.0, 0.04, 0.05))


def test_gpr_refuses_to_predict_before_fit():
    with pytest.raises(RuntimeError, match="before fit"):
        GPR(1.0, 1.0, 0.1).predict(np.zeros((1, 1)))


def test_scale_model_tables_equal_scikit_learns_after_updates():
    cfg = ScaleConfig()
    model = ScaleModel([2.0, 3.0], config=cfg)
    rng = np.random.default_rng(0)
    for _ in range(5):
        phase = rng.uniform(0, 1, 30)
        model.update(rng.normal(0, 4, (30, 2)), phase=phase)
    grid = np.linspace(0, 1, 101)
    log_l = _sklearn_means(model._x, model._y, grid.reshape(-1, 1), cfg.signal_var, cfg.length_scale,
                           cfg.noise_var) + np.log(model.default)
    np.testing.assert_array_equal(model(phase=grid), np.maximum(np.exp(log_l), cfg.min_scale))


def test_an_actor_learning_the_scale_does_not_import_scikit_learn():
    code = ("import sys, numpy as np; from khgrl.common.kmp.scale import ScaleModel; m = ScaleModel([1.0, 1.0]); "
            "m.update(np.ones((3, 2)) * 5, phase=np.array([0.1, 0.2, 0.3])); m(phase=0.5); "
            "print(sorted(k for k in sys.modules if k.split('.')[0] == 'sklearn'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
