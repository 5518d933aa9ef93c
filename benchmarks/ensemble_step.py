"""A raw-torch SAC gradient step with an ensemble of LayerNorm critics, batched (issue 23, item 7): the floor of what
an RLPD-style learner (Ball et al. 2023: E critics with LayerNorm, the target's min over 2 of them drawn at random,
the actor on the ensemble's mean) costs on this machine, for ``khgrl bench learner``.

The E critics are evaluated together, not in a Python loop: each layer keeps its weights stacked, (E, in, out), and
one ``torch.baddbmm`` computes every member's layer on the same minibatch; LayerNorm normalises each member's hidden
units and applies the member's own scale and shift. So an ensemble of E costs one batched matmul per layer, and
the benchmark can compare E = 10 with E = 1 directly (the issue's target: < 3x).
"""

from __future__ import annotations

import copy

import numpy as np

__all__ = ["EnsembleCritic", "RawEnsembleSAC", "mlp", "squashed_sample"]


def mlp(sizes: list[int]):
    """A ReLU MLP with ``sizes`` (input, hidden..., output) as a ``torch.nn.Sequential``."""
    import torch.nn as nn

    layers: list = []
    for a, b in zip(sizes[:-2], sizes[1:-1]):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers, nn.Linear(sizes[-2], sizes[-1]))


def squashed_sample(actor, obs):
    """SAC's squashed-Gaussian action and its log-probability from an actor that outputs (mean, log std)."""
    import torch

    mu, log_std = actor(obs).chunk(2, dim=-1)
    log_std = log_std.clamp(-20, 2)
    std = log_std.exp()
    u = mu + std * torch.randn_like(mu)
    a = torch.tanh(u)
    logp = (-0.5 * ((u - mu) / std) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
    return a, logp - torch.log(1 - a.pow(2) + 1e-6).sum(-1)


class EnsembleCritic:
    """E MLP critics Q(s, a) with stacked weights and LayerNorm after every hidden layer (ReLU after it).

    :param in_dim: observation + action size
    :param hidden: hidden layer sizes
    :param members: E
    :param device: torch device
    """

    def __init__(self, in_dim: int, hidden: tuple[int, ...], members: int, device: str) -> None:
        import torch

        self.torch, self.members = torch, members
        sizes = [in_dim, *hidden, 1]
        self.weights, self.biases, self.scales, self.shifts = [], [], [], []
        for a, b in zip(sizes[:-1], sizes[1:]):
            bound = 1.0 / np.sqrt(a)  # torch.nn.Linear's default initialisation, per member
            self.weights.append(torch.empty(members, a, b, device=device).uniform_(-bound, bound).requires_grad_())
            self.biases.append(torch.empty(members, 1, b, device=device).uniform_(-bound, bound).requires_grad_())
        for h in hidden:
            self.scales.append(torch.ones(members, 1, h, device=device, requires_grad=True))
            self.shifts.append(torch.zeros(members, 1, h, device=device, requires_grad=True))

    def parameters(self) -> list:
        return [*self.weights, *self.biases, *self.scales, *self.shifts]

    def __call__(self, x):
        """(B, in_dim) -> (E, B): every member's Q on the same minibatch."""
        torch = self.torch
        h = x.unsqueeze(0).expand(self.members, *x.shape)
        last = len(self.weights) - 1
        for k, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(b, h, w)
            if k < last:
                h = torch.nn.functional.layer_norm(h, h.shape[-1:]) * self.scales[k] + self.shifts[k]
                h = torch.relu(h)
        return h.squeeze(-1)


class RawEnsembleSAC:
    """SAC's gradient step written directly in torch with an :class:`EnsembleCritic` (RLPD's critic): squashed-Gaussian
    actor, learned entropy coefficient, the target's min over ``subset`` members drawn at random per step, the actor
    on the ensemble's mean, Polyak-averaged target critics.

    :param obs_dim: observation size
    :param act_dim: action size
    :param members: E critics
    :param subset: members in the target's min (RLPD: 2; clipped to E)
    :param hidden: hidden layer sizes of actor and critics
    :param device: torch device
    :param lr: Adam learning rate
    :param gamma: discount
    :param tau: Polyak rate
    """

    def __init__(self, obs_dim: int, act_dim: int, members: int = 10, subset: int = 2,
                 hidden: tuple[int, ...] = (256, 256), device: str = "cpu", lr: float = 3e-4, gamma: float = 0.99,
                 tau: float = 0.005) -> None:
        import torch

        self.torch, self.gamma, self.tau = torch, gamma, tau
        self.subset = min(subset, members)
        self.actor = mlp([obs_dim, *hidden, 2 * act_dim]).to(device)
        self.critic = EnsembleCritic(obs_dim + act_dim, hidden, members, device)
        self.target = copy.copy(self.critic)
        for name in ("weights", "biases", "scales", "shifts"):
            setattr(self.target, name, [p.detach().clone() for p in getattr(self.critic, name)])
        self.log_alpha = torch.zeros(1, device=device, requires_grad=True)
        self.target_entropy = -float(act_dim)
        self.opt_actor = torch.optim.Adam(self.actor.parameters(), lr=lr)
        self.opt_critic = torch.optim.Adam(self.critic.parameters(), lr=lr)
        self.opt_alpha = torch.optim.Adam([self.log_alpha], lr=lr)

    def step(self, obs, act, rew, next_obs, done) -> None:
        """One gradient step on a minibatch (tensors on the device)."""
        torch = self.torch
        alpha = self.log_alpha.detach().exp()
        with torch.no_grad():
            next_a, next_logp = squashed_sample(self.actor, next_obs)
            q_next = self.target(torch.cat([next_obs, next_a], dim=-1))  # (E, B)
            pick = torch.randperm(self.critic.members)[:self.subset]
            q_next = q_next[pick].min(dim=0).values - alpha * next_logp
            target = rew + (1 - done) * self.gamma * q_next
        q = self.critic(torch.cat([obs, act], dim=-1))
        critic_loss = 0.5 * (q - target[None]).pow(2).mean(dim=1).sum()
        self.opt_critic.zero_grad()
        critic_loss.backward()
        self.opt_critic.step()
        a, logp = squashed_sample(self.actor, obs)
        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        self.opt_alpha.zero_grad()
        alpha_loss.backward()
        self.opt_alpha.step()
        actor_loss = (alpha * logp - self.critic(torch.cat([obs, a], dim=-1)).mean(dim=0)).mean()
        self.opt_actor.zero_grad()
        actor_loss.backward()
        self.opt_actor.step()
        with torch.no_grad():
            for p, tp in zip(self.critic.parameters(), self.target.parameters()):
                tp.mul_(1 - self.tau).add_(p, alpha=self.tau)
