"""The learner's training iteration with each gradient step one CUDA graph (``--device cuda``, on by default;
``--no-cuda-graph``: SB3's own ``train()``, as on the CPU).

An iteration of G gradient steps (the run's ``gradient_steps``):

1. each step's minibatch is drawn on the host as SB3's buffer draws it (:meth:`~khgrl.learner.replay.
   StreamReplayBuffer.sample_into`, the same random numbers) into its rows of one pinned ``(G, B, W)`` array and
   copied to the device without blocking the host -- while the device still runs the step before: the host's
   sampling hides behind the device's work;
2. each step copies its minibatch into the static input rows on the device and replays the captured graph of
   :class:`~khgrl.learner.step.SB3Step` -- the library's gradient step (actor, entropy coefficient and critics,
   each with capturable Adam, and the Polyak update), all on the device -- and keeps its training scalars there;
3. once per iteration the host waits: the G steps' scalars, and whether every parameter is finite (one reduction
   over all of them on the device), come back in one copy; the scalars go to SB3's logger as SB3's ``train()``
   records them (``train/actor_loss`` ...: the means over the iteration), the flag to the trainer's fault check
   (:attr:`GraphedTrainer.finite`: no second sync unless something is not finite).

The graph is captured after :data:`WARMUP` eager steps (which initialise the optimisers' state and the CUDA
libraries' workspaces) and again whenever the learning rates change (SB3's schedule; the run's is constant).
Distribution argument checks (a host sync) are off inside it: a NaN parameter shows as a NaN loss, which the
trainer's :meth:`~khgrl.learner.algorithm.LearnerAlgorithm.fault` finds and rolls back. The rollback snapshot is
copied into preallocated device tensors and back in place (:meth:`GraphedTrainer.snapshot`), so the tensors the
graph reads and writes stay the ones it was captured with. The same bookkeeping runs eagerly where no graph is
wanted (``graph=False``, e.g. on the CPU in the tests): then each step is the step function, called.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np
from khgrl.learner.step import SCALARS, Minibatch, SB3Step

__all__ = ["GraphedTrainer", "WARMUP", "set_capturable", "optimizers"]

WARMUP = 3  # eager steps before the capture (torch's advice for whole-network capture)


def optimizers(model: Any) -> list[Any]:
    """The optimisers a training iteration steps: the actor's, the critics' and the entropy coefficient's."""
    found = (model.actor.optimizer, model.critic.optimizer, getattr(model, "ent_coef_optimizer", None))
    return [opt for opt in found if opt is not None]


def set_capturable(model: Any, on: bool) -> None:
    """Make the model's Adam optimisers capturable (their step counters moved to the parameters' device, as a CUDA
    graph needs) or say they are not (the flag alone: what a checkpoint says, so that it loads anywhere -- SB3 maps
    the counters to the device it loads on; the tensors stay where they are, and so stay the graphs' own).

    :param model: the SB3 model
    :param on: capturable or not
    """
    for opt in optimizers(model):
        for group in opt.param_groups:
            group["capturable"] = on
            for p in group["params"] if on else ():
                state = opt.state.get(p)
                if state and "step" in state and state["step"].device != p.device:
                    state["step"] = state["step"].to(p.device)


@contextmanager
def no_distribution_checks() -> Iterator[None]:
    """torch.distributions without argument validation (a host sync, not allowed while capturing)."""
    from torch.distributions import Distribution

    before = Distribution._validate_args
    Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        Distribution.set_default_validate_args(before)


class GraphedTrainer:
    """SB3's ``train(gradient_steps, batch_size)`` for a SAC or TQC model, each step a replayed CUDA graph (the
    module docstring).

    :param model: the SB3 model (its replay buffer a :class:`~khgrl.learner.replay.StreamReplayBuffer`)
    :param graph: capture CUDA graphs (needs the model on a CUDA device); False: the same iteration, eager
    :param compile_loss: eager only: TQC's loss compiled (:class:`~khgrl.learner.step.SB3Step`)
    """

    def __init__(self, model: Any, graph: bool = True, compile_loss: bool = False) -> None:
        import torch

        self.model, self.step = model, SB3Step(model, compile_loss=compile_loss and not graph)
        self.device = torch.device(model.device)
        self.graph = bool(graph)
        if self.graph and self.device.type != "cuda":
            raise ValueError(f"CUDA graphs need a CUDA device, not {self.device}")
        rb = model.replay_buffer
        self.obs_dim, self.act_dim, self.width = int(rb.obs_shape[0]), int(rb.action_dim), rb.minibatch_width()
        self.batch_size = int(model.batch_size)
        self.host: Any = None  # pinned (G, B, W) host rows, and their numpy view
        self.host_np: np.ndarray | None = None
        self.staged: Any = None  # (G, B, W) on the device
        self.static = torch.zeros((self.batch_size, self.width), device=self.device)  # the graphs' input
        self.graphs: dict[bool, tuple[Any, Any]] = {}  # polyak? -> (graph, its scalars tensor)
        self.lrs: tuple[float, ...] = ()
        self.eager_steps = 0
        self.captures = 0
        self.side: Any = None  # the warm-up steps' stream
        self._snap: list[Any] | None = None
        self._live_cache: list[Any] | None = None
        self.finite: bool | None = None  # every parameter finite after the last iteration (None: not known)
        if self.graph:
            set_capturable(model, True)

    # ------------------------------------------------------------------------------------ one iteration
    def train(self, gradient_steps: int) -> np.ndarray:
        """``gradient_steps`` steps on minibatches drawn from the model's buffer (within its ``sample_limit``);
        records SB3's training scalars and returns them, one row per step (:data:`~khgrl.learner.step.SCALARS`).

        :param gradient_steps: how many (the run's G)
        """
        import torch

        m = self.model
        m.policy.set_training_mode(True)
        m._update_learning_rate(optimizers(m))
        lrs = tuple(float(g["lr"]) for opt in optimizers(m) for g in opt.param_groups)
        if lrs != self.lrs:  # (captured with the old rates: capture again)
            self.graphs.clear()
            self.lrs = lrs
        self.finite = None
        self._buffers(gradient_steps)
        scalars = torch.empty((gradient_steps, len(SCALARS)), device=self.device, dtype=self.static.dtype)
        with no_distribution_checks() if self.graph else _nothing():
            for k in range(gradient_steps):
                scalars[k] = self._one(self._draw(k), k % m.target_update_interval == 0)
        params = self.parameters()
        finite = torch.isfinite(torch.cat([t.reshape(-1) for t in params])).all().reshape(1)
        back = torch.cat([scalars.reshape(-1).double(), finite.double()]).cpu().numpy()  # the iteration's one sync
        values, self.finite = back[:-1].reshape(gradient_steps, len(SCALARS)), bool(back[-1])
        m._n_updates += gradient_steps
        mean = dict(zip(SCALARS, values.mean(axis=0).tolist()))
        m.logger.record("train/n_updates", m._n_updates, exclude="tensorboard")
        for name in ("ent_coef", "actor_loss", "critic_loss"):
            m.logger.record(f"train/{name}", mean[name])
        if m.ent_coef_optimizer is not None:
            m.logger.record("train/ent_coef_loss", mean["ent_coef_loss"])
        return values

    def _buffers(self, n: int) -> None:
        """The pinned host rows and their device copy for ``n`` minibatches (made when ``n`` changes)."""
        import torch

        if self.host is None or len(self.host) != n:
            pin = self.device.type == "cuda"
            self.host = torch.empty((n, self.batch_size, self.width), dtype=torch.float32, pin_memory=pin)
            self.host_np = self.host.numpy()
            self.staged = torch.empty((n, self.batch_size, self.width), device=self.device)

    def _draw(self, k: int) -> Any:
        """Step ``k``'s minibatch drawn into its pinned host rows and copied (not blocking) to the device. (Its rows
        are rewritten only in the next iteration, after that iteration's sync: the copy has long finished.)"""
        self.model.replay_buffer.sample_into(self.host_np[k])
        if self.device.type != "cuda":
            return self.host[k]
        self.staged[k].copy_(self.host[k], non_blocking=True)
        return self.staged[k]

    def _one(self, rows: Any, polyak: bool) -> Any:
        """One step on ``rows``: the captured graph replayed, or (warming up, or without graphs) the step function."""
        if not self.graph:
            self.eager_steps += 1
            return self.step(Minibatch.split(rows, self.obs_dim, self.act_dim), polyak)
        import torch

        if self.eager_steps < WARMUP:  # eager, on a side stream (torch's capture recipe)
            if self.side is None:
                self.side = torch.cuda.Stream(self.device)
            side = self.side
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(side):
                self.static.copy_(rows)
                out = self.step(Minibatch.split(self.static, self.obs_dim, self.act_dim), polyak)
            torch.cuda.current_stream(self.device).wait_stream(side)
            self.eager_steps += 1
            return out
        if polyak not in self.graphs:
            self.graphs[polyak] = self._capture(polyak)
        graph, out = self.graphs[polyak]
        self.static.copy_(rows)
        graph.replay()
        return out

    def _capture(self, polyak: bool) -> tuple[Any, Any]:
        """One gradient step captured as a CUDA graph reading :attr:`static` (nothing runs: the caller replays)."""
        import torch

        torch.cuda.synchronize(self.device)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, capture_error_mode="thread_local"):  # (the ingest thread runs on meanwhile)
            out = self.step(Minibatch.split(self.static, self.obs_dim, self.act_dim), polyak)
        self.captures += 1
        return graph, out

    def invalidate(self) -> None:
        """Forget the captured graphs (the optimisers' state tensors were replaced: captured again when next due)."""
        self.graphs.clear()
        self._snap = self._live_cache = self.finite = None

    def parameters(self) -> list[Any]:
        """The floating-point tensors :meth:`~khgrl.learner.sb3_offpolicy.SB3OffPolicy.fault` checks: the policy's
        (networks, target networks) and the entropy coefficient."""
        m = self.model
        out = [t.detach() for t in m.policy.state_dict(keep_vars=True).values() if t.is_floating_point()]
        if getattr(m, "log_ent_coef", None) is not None:
            out.append(m.log_ent_coef.detach())
        return out

    # ------------------------------------------------------------------------------------ rollback in place
    def _live(self) -> list[Any] | None:
        """The tensors an iteration changes (networks, target networks, entropy coefficient, optimiser state), or
        None before the optimisers have state (kept until :meth:`invalidate`: the same tensors all along)."""
        if self._live_cache is not None:
            return self._live_cache
        m = self.model
        live = [t for t in m.policy.state_dict(keep_vars=True).values()]
        if getattr(m, "log_ent_coef", None) is not None:
            live.append(m.log_ent_coef)
        for opt in optimizers(m):
            for group in opt.param_groups:
                for p in group["params"]:
                    state = opt.state.get(p)
                    if not state:
                        return None
                    live.extend(v for v in state.values() if hasattr(v, "copy_"))
        self._live_cache = [t.detach() for t in live]
        return self._live_cache

    def snapshot(self) -> dict[str, Any] | None:
        """The iteration's state copied into preallocated tensors on the device (one batched copy); None where
        the optimisers have no state yet (the caller takes SB3's generic snapshot)."""
        import torch

        live = self._live()
        if live is None:
            return None
        if self._snap is None or len(self._snap) != len(live):
            self._snap = [torch.empty_like(t) for t in live]
        torch._foreach_copy_(self._snap, live)
        return {"graphed": True, "n_updates": self.model._n_updates}

    def restore(self, snapshot: dict[str, Any]) -> None:
        """Copy :meth:`snapshot`'s tensors back in place (the graphs keep their tensors).

        :param snapshot: what :meth:`snapshot` returned
        """
        import torch

        live = self._live()
        if live is None or self._snap is None or len(live) != len(self._snap):
            raise RuntimeError("the graphed learner's snapshot no longer fits its model")
        with torch.no_grad():
            torch._foreach_copy_(live, self._snap)
        self.model._n_updates = snapshot["n_updates"]
        self.finite = None


@contextmanager
def _nothing() -> Iterator[None]:
    yield
