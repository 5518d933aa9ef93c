"""The batched LayerNorm critic ensemble of ``khgrl bench learner`` (benchmarks/ensemble_step.py): one batched
evaluation equals each member computed on its own, and a gradient step changes every member and stays finite."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from khgrl.benchmarks.ensemble_step import EnsembleCritic, RawEnsembleSAC  # noqa: E402


def test_batched_members_equal_members_one_by_one() -> None:
    torch.manual_seed(0)
    critic = EnsembleCritic(7, (16, 16), members=5, device="cpu")
    with torch.no_grad():
        for s in critic.scales + critic.shifts:  # members differ in their LayerNorm affine too
            s.add_(0.1 * torch.randn_like(s))
    x = torch.randn(9, 7)
    got = critic(x).detach()
    for k in range(5):
        h = x
        for j, (w, b) in enumerate(zip(critic.weights, critic.biases)):
            h = h @ w[k].detach() + b[k, 0].detach()
            if j < len(critic.weights) - 1:
                mu, var = h.mean(-1, keepdim=True), h.var(-1, unbiased=False, keepdim=True)
                h = torch.relu((h - mu) / torch.sqrt(var + 1e-5) * critic.scales[j][k, 0].detach()
                               + critic.shifts[j][k, 0].detach())
        np.testing.assert_allclose(got[k].numpy(), h[:, 0].numpy(), rtol=1e-5, atol=1e-5)


def test_a_step_trains_every_member_and_stays_finite() -> None:
    torch.manual_seed(1)
    sac = RawEnsembleSAC(5, 2, members=4, hidden=(32, 32))
    before = [w.detach().clone() for w in sac.critic.weights]
    batch = (torch.randn(64, 5), torch.rand(64, 2) * 2 - 1, torch.randn(64), torch.randn(64, 5), torch.zeros(64))
    for _ in range(3):
        sac.step(*batch)
    for b, w in zip(before, sac.critic.weights):
        assert all(not torch.equal(b[k], w[k]) for k in range(4))
        assert torch.isfinite(w).all()
    assert all(not torch.equal(t, p) for t, p in zip(sac.target.parameters(), sac.critic.parameters()))
