"""The graphed sides of ``khgrl bench learner``: the learner's training iteration as the learner runs it with
``--cuda-graph`` (:mod:`khgrl.learner.cuda_graph`: snapshot, G graphed steps, one host sync, fault check -- what
:meth:`~khgrl.learner.trainer.Trainer._iterate` does), the same iteration eager (the step function called, on any
device: what the CPU would run), and a bare CUDA graph of the raw-torch TQC step (:class:`~khgrl.benchmarks.
learner_step.RawTQC` with capturable Adam, its minibatch drawn on the device inside the graph): the ceiling the
learner's graphed step is held to (issue 39: at least 0.85 of it)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Callable

import numpy as np

__all__ = ["learner_iteration", "raw_graph_learner"]


def learner_iteration(obs_dim: int, act_dim: int, device: str, size: int, seed: int, algo: str = "tqc",
                      sampling: str = "uniform", graph: bool = True,
                      compile_loss: bool = False) -> Callable[[int], None]:
    """The learner's algorithm (``algo``, ``sampling``) with a filled buffer (``size`` random transitions, every
    tenth intervened), trained through :class:`~khgrl.learner.cuda_graph.GraphedTrainer`; returns a callable doing
    ``n`` gradient steps as one learner iteration (snapshot, train, fault check).

    :param graph: CUDA graphs (cuda only); False: the same iteration with the step function called eagerly
    :param compile_loss: (cpu) TQC's loss compiled (``--compile-loss``)
    """
    from khgrl.common.config.settings import TQCSettings
    from khgrl.learner.cuda_graph import GraphedTrainer
    from khgrl.learner.trainer import build_algorithm
    from stable_baselines3.common.logger import configure

    task = SimpleNamespace(out_dim=act_dim, obs_low=[-10.0] * obs_dim, obs_high=[10.0] * obs_dim)  # spaces only
    settings = TQCSettings(device=device, learning_starts=0, sampling=sampling, cuda_graph=graph,
                           compile_loss=compile_loss)
    learner = build_algorithm(settings, seed, task, algo)
    learner.model.set_logger(configure(None, []))
    if learner.graphed is None:
        learner.graphed = GraphedTrainer(learner.model, graph=graph)
    rng = np.random.default_rng(seed)
    learner.store(rng.normal(size=(size, obs_dim)).astype(np.float32),
                  rng.normal(size=(size, obs_dim)).astype(np.float32),
                  rng.uniform(-1, 1, (size, act_dim)).astype(np.float32), rng.normal(size=size).astype(np.float32),
                  (np.arange(size) % 100 == 99).astype(np.float32), np.zeros(size, np.float32),
                  intervened=(np.arange(size) % 10 == 0).astype(np.uint8), clipped=np.zeros(size, np.uint8), actor=0,
                  first_step=0)

    def steps(n: int) -> None:
        before = learner.snapshot()
        learner.train(n, timestep=size, sample_limit=None)
        if learner.fault() is not None:
            learner.restore(before)
    return steps


def raw_graph_learner(raw_class: type, obs_dim: int, act_dim: int, size: int, seed: int,
                      batch: int = 256) -> Callable[[int], None]:
    """A raw-torch step (``raw_class``: :class:`~khgrl.benchmarks.learner_step.RawTQC`) on cuda, its step
    (minibatch drawn on the device from a replay held there, capturable Adam) captured once as a CUDA graph;
    returns a callable replaying it ``n`` times (the caller synchronises)."""
    import torch

    torch.manual_seed(seed)
    raw = raw_class(obs_dim, act_dim, device="cuda")
    for opt in (raw.opt_actor, raw.opt_critic, raw.opt_alpha):
        for group in opt.param_groups:
            group["capturable"] = True
    data = [torch.randn(size, obs_dim, device="cuda"), torch.rand(size, act_dim, device="cuda") * 2 - 1,
            torch.randn(size, device="cuda"), torch.randn(size, obs_dim, device="cuda"),
            (torch.arange(size, device="cuda") % 100 == 99).float()]

    def one() -> None:
        idx = torch.randint(0, size, (batch,), device="cuda")
        raw.step(*(x[idx] for x in data))

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            one()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        one()

    def steps(n: int) -> None:
        for _ in range(n):
            graph.replay()
    return steps
