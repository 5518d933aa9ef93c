"""The learner's gradient step (``khgrl bench learner``): sb3-contrib TQC as the learner runs it, next to a minimal
raw-torch TQC step of the same networks, on each device asked for (``cpu``, and ``cuda`` where torch sees a GPU);
beside them the learner's SAC (``--algo sac``), HIL-SERL's SAC (``--algo sac_ln``: LayerNorm, tanh) with SB3's
uniform sampling and with RLPD's symmetric sampling (``--sampling rlpd``, a tenth of the stored transitions
intervened: what the prior half of each minibatch costs), and a raw-torch SAC step with an ensemble of LayerNorm
critics, batched (:mod:`khgrl.benchmarks.ensemble_step`), for each ``--ensembles`` size: what an RLPD-style learner
costs.

Both sides do the same work per gradient step: a minibatch of ``batch_size`` sampled from a filled replay buffer,
the truncated quantile critics' loss (2 critics x 25 quantiles, the top 2 per net dropped), the actor's loss, the
entropy coefficient's loss, three Adam steps and the Polyak update of the target critics (TQC's defaults, the
paper's 2 x 256 networks, batch 256). The raw step is the floor: what the arithmetic costs without SB3's
bookkeeping. The two are timed in alternating slices in one process with the same torch thread count, so that a
noisy, shared machine affects both alike; the ratio is what to compare across machines.

Run it on a machine with a GPU to see what ``--device cuda`` buys the learner::

    khgrl bench learner --devices cpu cuda --seconds 20
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import numpy as np
from khgrl.benchmarks.ensemble_step import mlp as _mlp
from khgrl.benchmarks.ensemble_step import squashed_sample

__all__ = ["run_learner_benchmark", "RawTQC"]

N_QUANTILES, N_CRITICS, DROP_PER_NET = 25, 2, 2  # sb3-contrib TQC's defaults


class RawTQC:
    """TQC's gradient step written directly in torch (no SB3): squashed-Gaussian actor, truncated quantile
    critics, learned entropy coefficient, Polyak-averaged target critics.

    :param obs_dim: observation size
    :param act_dim: action size
    :param hidden: hidden layer sizes of actor and critics
    :param device: torch device
    :param lr: Adam learning rate
    :param gamma: discount
    :param tau: Polyak rate
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...] = (256, 256), device: str = "cpu",
                 lr: float = 1e-3, gamma: float = 0.99, tau: float = 0.02) -> None:
        import copy

        import torch

        self.torch, self.device, self.gamma, self.tau = torch, device, gamma, tau
        self.actor = _mlp([obs_dim, *hidden, 2 * act_dim]).to(device)
        self.critics = torch.nn.ModuleList(_mlp([obs_dim + act_dim, *hidden, N_QUANTILES])
                                           for _ in range(N_CRITICS)).to(device)
        self.target = copy.deepcopy(self.critics)
        self.log_alpha = torch.zeros(1, device=device, requires_grad=True)
        self.target_entropy = -float(act_dim)
        self.opt_actor = torch.optim.Adam(self.actor.parameters(), lr=lr)
        self.opt_critic = torch.optim.Adam(self.critics.parameters(), lr=lr)
        self.opt_alpha = torch.optim.Adam([self.log_alpha], lr=lr)
        tau_q = (torch.arange(N_QUANTILES, device=device, dtype=torch.float32) + 0.5) / N_QUANTILES
        self.tau_q = tau_q.view(1, 1, -1, 1)
        self.keep = N_QUANTILES * N_CRITICS - DROP_PER_NET * N_CRITICS

    def _act(self, obs):
        return squashed_sample(self.actor, obs)

    def _quantiles(self, nets, obs, act):
        x = self.torch.cat([obs, act], dim=-1)
        return self.torch.stack([q(x) for q in nets], dim=1)  # (B, critics, quantiles)

    def step(self, obs, act, rew, next_obs, done) -> None:
        """One gradient step on a minibatch (tensors on ``device``)."""
        torch = self.torch
        alpha = self.log_alpha.detach().exp()
        with torch.no_grad():
            next_a, next_logp = self._act(next_obs)
            z = self._quantiles(self.target, next_obs, next_a).reshape(len(obs), -1)
            z = torch.sort(z, dim=1).values[:, :self.keep] - alpha * next_logp[:, None]
            target = rew[:, None] + (1 - done[:, None]) * self.gamma * z
        q = self._quantiles(self.critics, obs, act)
        diff = target[:, None, None, :] - q[:, :, :, None]
        huber = torch.where(diff.abs() <= 1, 0.5 * diff.pow(2), diff.abs() - 0.5)
        critic_loss = ((self.tau_q - (diff.detach() < 0).float()).abs() * huber).mean()
        self.opt_critic.zero_grad()
        critic_loss.backward()
        self.opt_critic.step()
        a, logp = self._act(obs)
        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        self.opt_alpha.zero_grad()
        alpha_loss.backward()
        self.opt_alpha.step()
        actor_loss = (alpha * logp - self._quantiles(self.critics, obs, a).mean(dim=(1, 2))).mean()
        self.opt_actor.zero_grad()
        actor_loss.backward()
        self.opt_actor.step()
        with torch.no_grad():
            for p, tp in zip(self.critics.parameters(), self.target.parameters()):
                tp.mul_(1 - self.tau).add_(p, alpha=self.tau)


def _sb3_learner(obs_dim: int, act_dim: int, device: str, size: int, seed: int, algo: str = "tqc",
                 sampling: str = "uniform"):
    """The learner's own model (``--algo``: ``tqc``, ``sac``, ``sac_ln``; ``--sampling``) on a task of these sizes,
    its buffer filled with ``size`` random transitions, every tenth intervened; returns a callable doing ``n``
    gradient steps as the learner's training iteration does."""
    from types import SimpleNamespace

    from khgrl.common.config.settings import TQCSettings
    from khgrl.learner.trainer import build_algorithm
    from stable_baselines3.common.logger import configure

    task = SimpleNamespace(out_dim=act_dim, obs_low=[-10.0] * obs_dim, obs_high=[10.0] * obs_dim)  # spaces only
    model = build_algorithm(TQCSettings(device=device, learning_starts=0, sampling=sampling), seed, task, algo).model
    model.set_logger(configure(None, []))
    rng = np.random.default_rng(seed)
    rb = model.replay_buffer
    for i in range(size):
        rb.add(rng.normal(size=(1, obs_dim)), rng.normal(size=(1, obs_dim)), rng.uniform(-1, 1, (1, act_dim)),
               rng.normal(size=1), np.array([float(i % 100 == 99)]), [{}], intervened=i % 10 == 0, clipped=False,
               actor=0, step=i)

    def steps(n: int) -> None:
        model.train(gradient_steps=n, batch_size=model.batch_size)
    return steps


def _raw_learner(obs_dim: int, act_dim: int, device: str, size: int, seed: int, members: int | None = None,
                 batch: int = 256):
    """A raw-torch learner (:class:`RawTQC`, or with ``members`` :class:`~khgrl.benchmarks.ensemble_step.RawEnsembleSAC`
    with that many LayerNorm critics) on ``size`` random transitions; returns a callable doing ``n`` gradient steps."""
    import torch
    from khgrl.benchmarks.ensemble_step import RawEnsembleSAC

    torch.manual_seed(seed)
    raw = RawTQC(obs_dim, act_dim, device=device) if members is None else RawEnsembleSAC(
        obs_dim, act_dim, members=members, device=device)
    g = torch.Generator(device="cpu").manual_seed(seed)
    data = [torch.randn(size, obs_dim), torch.rand(size, act_dim) * 2 - 1, torch.randn(size),
            torch.randn(size, obs_dim), (torch.arange(size) % 100 == 99).float()]

    def steps(n: int) -> None:
        for _ in range(n):
            idx = torch.randint(0, size, (batch,), generator=g)
            raw.step(*(x[idx].to(device, non_blocking=True) for x in data))
    return steps


def _sides(obs_dim: int, act_dim: int, device: str, seed: int, ensembles: tuple[int, ...]) -> dict:
    """The learners timed against each other: the learner's TQC, SAC and SAC-LN (uniform and RLPD sampling) with
    SB3's ``train()``, and each as the learner's iteration with the step function (:mod:`khgrl.benchmarks.
    graph_step`: on cuda one CUDA graph per step, ``graph_*``; on every device called eagerly, ``stepfn_tqc``),
    raw-torch TQC (on cuda also as a bare CUDA graph, ``raw_graph``), and raw-torch SAC with each ensemble size."""
    from khgrl.benchmarks.graph_step import learner_iteration, raw_graph_learner

    sides = {"stepfn_tqc": learner_iteration(obs_dim, act_dim, device, 20_000, seed, graph=False)}
    if device == "cpu":  # (--compile-loss: the CPU only)
        sides["stepfn_tqc_compiled"] = learner_iteration(obs_dim, act_dim, device, 20_000, seed, graph=False,
                                                         compile_loss=True)
    if device == "cuda":
        sides["raw_graph"] = raw_graph_learner(RawTQC, obs_dim, act_dim, 20_000, seed)
        for algo, sampling in (("tqc", "uniform"), ("sac", "uniform"), ("sac_ln", "uniform"), ("sac_ln", "rlpd")):
            name = f"graph_{algo}" + ("_rlpd" if sampling == "rlpd" else "")
            sides[name] = learner_iteration(obs_dim, act_dim, device, 20_000, seed, algo, sampling)
    sides |= {"sb3_tqc": _sb3_learner(obs_dim, act_dim, device, 20_000, seed),
             "raw_torch": _raw_learner(obs_dim, act_dim, device, 20_000, seed),
             "sb3_sac": _sb3_learner(obs_dim, act_dim, device, 20_000, seed, "sac"),
             "sb3_sac_ln": _sb3_learner(obs_dim, act_dim, device, 20_000, seed, "sac_ln"),
             "sb3_sac_ln_rlpd": _sb3_learner(obs_dim, act_dim, device, 20_000, seed, "sac_ln", "rlpd")}
    for e in ensembles:
        sides[f"raw_sac_ln_e{e}"] = _raw_learner(obs_dim, act_dim, device, 20_000, seed, e)
    return sides


def _timed(fn, seconds: float, chunk: int, device: str) -> tuple[int, float]:
    import torch

    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        fn(chunk)
        n += chunk
    if device == "cuda":
        torch.cuda.synchronize()
    return n, time.perf_counter() - t0


def run_learner_benchmark(devices: tuple[str, ...] = ("cpu",), seconds: float = 20.0, rounds: int = 3,
                          obs_dim: int = 32, act_dim: int = 3, threads: int = 1, seed: int = 0,
                          ensembles: tuple[int, ...] = (1, 10), out: str | None = None) -> dict:
    """Gradient steps per second of the learner's TQC and of :class:`RawTQC`, per device; prints a table.

    :param devices: torch devices to measure ('cuda' is skipped with a note where torch sees no GPU)
    :param seconds: time per side and device, split into ``rounds`` alternating slices
    :param rounds: alternating slices per side
    :param obs_dim: observation size (default: the Fetch task's 32)
    :param act_dim: action size (default 3)
    :param threads: torch threads (the learner's default: 1)
    :param seed: seed
    :param ensembles: critic ensemble sizes of the raw-torch SAC step (issue 23: 10 critics vs 1)
    :param out: also write the results as JSON here
    """
    import torch

    torch.set_num_threads(threads)
    results: dict = {"machine": {"host": platform.node(), "cpu": platform.processor() or platform.machine(),
                                 "torch": torch.__version__, "threads": threads, "load": _load()},
                     "obs_dim": obs_dim, "act_dim": act_dim, "batch": 256, "devices": {}}
    for device in devices:
        if device == "cuda" and not torch.cuda.is_available():
            print("cuda: torch sees no GPU here; skipped")
            continue
        sides = _sides(obs_dim, act_dim, device, seed, ensembles)
        for fn in sides.values():
            fn(8)  # warm-up (allocations, cuda kernels)
        counts = {k: [0, 0.0] for k in sides}
        for _ in range(rounds):
            for name, fn in sides.items():
                n, dt = _timed(fn, seconds / rounds, 8, device)
                counts[name][0] += n
                counts[name][1] += dt
        rate = {k: n / dt for k, (n, dt) in counts.items()}
        results["devices"][device] = {**{f"{k}_steps_per_s": round(v, 1) for k, v in rate.items()},
                                      "sb3_over_raw": round(rate["sb3_tqc"] / rate["raw_torch"], 3)}
        _print_graphed(device, rate, results["devices"][device])
        print(f"{device}: learner TQC {rate['sb3_tqc']:.1f} gradient steps/s, raw torch {rate['raw_torch']:.1f} "
              f"steps/s: ratio {rate['sb3_tqc'] / rate['raw_torch']:.2f}; learner SAC {rate['sb3_sac']:.1f} steps/s")
        print(f"{device}: learner SAC-LN (HIL-SERL's) {rate['sb3_sac_ln']:.1f} steps/s uniform, "
              f"{rate['sb3_sac_ln_rlpd']:.1f} steps/s with RLPD sampling "
              f"({rate['sb3_sac_ln'] / rate['sb3_sac_ln_rlpd']:.2f}x the time)")
        for e in ensembles:
            r = rate[f"raw_sac_ln_e{e}"]
            print(f"{device}: raw SAC, {e} LayerNorm critics (batched): {r:.1f} steps/s"
                  + (f" = {rate[f'raw_sac_ln_e{ensembles[0]}'] / r:.2f}x the time of {ensembles[0]}"
                     if e != ensembles[0] else ""))
    if "cpu" in results["devices"] and "cuda" in results["devices"]:
        c, g = results["devices"]["cpu"], results["devices"]["cuda"]
        print(f"cuda / cpu (learner TQC): {g['sb3_tqc_steps_per_s'] / c['sb3_tqc_steps_per_s']:.2f}x")
    results["machine"]["load_after"] = _load()
    if out:
        Path(out).write_text(json.dumps(results, indent=2))
        print(f"wrote {out}")
    return results


def _print_graphed(device: str, rate: dict, row: dict) -> None:
    """The step function's lines: eager (every device) and graphed (cuda), against SB3's ``train()``."""
    print(f"{device}: learner TQC iteration with the step function, eager: {rate['stepfn_tqc']:.1f} steps/s "
          f"({rate['stepfn_tqc'] / rate['sb3_tqc']:.2f}x SB3's train())")
    row["stepfn_over_sb3"] = round(rate["stepfn_tqc"] / rate["sb3_tqc"], 3)
    if "stepfn_tqc_compiled" in rate:
        row["compiled_over_sb3"] = round(rate["stepfn_tqc_compiled"] / rate["sb3_tqc"], 3)
        print(f"{device}: learner TQC iteration with its loss compiled (--compile-loss, opt-in): "
              f"{rate['stepfn_tqc_compiled']:.1f} steps/s ({row['compiled_over_sb3']:.2f}x SB3's train())")
    if "graph_tqc" not in rate:
        return
    row["graph_over_eager"] = round(rate["graph_tqc"] / rate["sb3_tqc"], 3)
    row["graph_over_bare_graph"] = round(rate["graph_tqc"] / rate["raw_graph"], 3)
    print(f"{device}: learner TQC, one CUDA graph per step: {rate['graph_tqc']:.1f} steps/s = "
          f"{row['graph_over_eager']:.2f}x eager SB3, {row['graph_over_bare_graph']:.2f}x a bare graph of the raw "
          f"step ({rate['raw_graph']:.1f}); graphed SAC {rate['graph_sac']:.1f}, SAC-LN {rate['graph_sac_ln']:.1f}, "
          f"SAC-LN with RLPD sampling {rate['graph_sac_ln_rlpd']:.1f} steps/s")


def _load() -> list[float]:
    import os

    return [round(x, 2) for x in os.getloadavg()]
