"""The learner watches its critic: Q beyond what the task's reward bound and gamma allow rolls the iteration back.

With every reward within +-r_max (the task descriptor's ``reward_bound``: the environment's bound plus the largest
action cost), every discounted return lies within +-r_max / (1 - gamma). A critic whose Q on the stored transitions
goes beyond twice that, :attr:`CriticWatch.q_max` = 2 r_max / (1 - gamma), has learned something no transition of
the task can give: rewards near the bound stored by an actor that holds the run's keys (issue 34 point 5: the
critic's Q on the honest actor's states went from -15 to +2.4 million and the policy saturated on all of them), or
a divergence. After each training iteration that left everything finite, :meth:`CriticWatch.check` evaluates the
critic on up to :data:`ROWS` stored transitions (their observations and actions; evenly spaced over the rows the
iteration could sample, so no random number is drawn and a seeded run is unchanged); beyond ``q_max`` the trainer
restores the iteration's snapshot (the same rollback as a non-finite loss, :mod:`khgrl.learner.trainer`) and
counts it (``q_rollbacks`` in the learner's summary). The check costs one forward pass of the critics on
:data:`ROWS` rows, once per iteration (timed: :attr:`CriticWatch.seconds`).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

__all__ = ["CriticWatch", "ROWS", "q_limit", "critic_values"]

log = logging.getLogger("khgrl.learner")

ROWS = 256  # stored transitions the critic is evaluated on after each iteration


def q_limit(reward_bound: float, gamma: float) -> float:
    """Q_max = 2 r_max / (1 - gamma): twice the largest |discounted return| rewards within +-r_max allow.

    :param reward_bound: r_max, the task descriptor's ``reward_bound``.
    :param gamma: the discount factor (< 1).
    """
    return 2.0 * float(reward_bound) / max(1.0 - float(gamma), 1e-9)


def critic_values(model: Any, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Every critic's Q (each of TQC's quantiles) for the rows ``obs`` (n, obs_dim), ``actions`` (n, O):
    (n, k) float64, under ``torch.no_grad``.

    :param model: the SB3 model (TQC: ``critic`` gives (n, critics, quantiles); SAC: a tuple of (n, 1)).
    :param obs: observations (a camera task's: a Dict of its state vectors and images).
    :param actions: the stored (scaled) actions.
    """
    import torch

    with torch.no_grad():
        if isinstance(obs, dict):  # a camera task's: images stay uint8, the encoder scales them
            o = {k: torch.as_tensor(v, device=model.device) for k, v in obs.items()}
        else:
            o = torch.as_tensor(obs, dtype=torch.float32, device=model.device)
        a = torch.as_tensor(actions, dtype=torch.float32, device=model.device)
        n = len(a)
        q = model.critic(o, a)
        q = torch.cat([t.reshape(n, -1) for t in q], dim=1) if isinstance(q, (tuple, list)) else q
        return q.reshape(n, -1).double().cpu().numpy()


class CriticWatch:
    """Checks the critic after each training iteration against :func:`q_limit` (the module docstring).

    :param reward_bound: the task descriptor's ``reward_bound`` (r_max).
    :param rows: how many stored transitions to evaluate.
    """

    def __init__(self, reward_bound: float, rows: int = ROWS) -> None:
        self.reward_bound = float(reward_bound)
        self.rows = int(rows)
        self.rollbacks = 0  # iterations rolled back for a Q beyond q_max
        self.last = ""  # what the last one found
        self.largest = 0.0  # the largest |Q| seen by a check (rolled back or not)
        self.seconds = 0.0  # time spent in the checks
        self.checks = 0

    def summary(self) -> dict:
        """The largest |Q| and the time per check (ms), once there has been a check (else empty)."""
        if not self.checks:
            return {}
        return {"q_largest": float(f"{self.largest:.4g}"), "q_check_ms": round(1e3 * self.seconds / self.checks, 2)}

    def q_max(self, gamma: float) -> float:
        """:func:`q_limit` of this task's reward bound and ``gamma``."""
        return q_limit(self.reward_bound, gamma)

    def _rows(self, buffer: Any, limit: int | None) -> np.ndarray:
        """Up to :attr:`rows` slots, evenly spaced over those the iteration could sample."""
        upper = buffer.buffer_size if buffer.full else int(buffer.pos)
        if limit is not None and not buffer.full:
            upper = min(upper, int(limit))
        if upper <= 0:
            return np.zeros(0, dtype=np.int64)
        return np.unique(np.linspace(0, upper - 1, min(self.rows, upper)).round().astype(np.int64))

    def check(self, algo: Any, limit: int | None) -> str | None:
        """Why the iteration just trained must be rolled back (the largest |Q| and where), or None.

        :param algo: the learner algorithm (an SB3 one: its ``model`` with ``critic``, ``gamma``, replay buffer).
        :param limit: the iteration's ``sample_limit`` (None: every stored row).
        """
        model = getattr(algo, "model", None)
        if model is None or getattr(model, "critic", None) is None:
            return None
        t0 = time.perf_counter()
        rb = algo.buffer
        with rb.lock:
            rows = self._rows(rb, limit)
            obs, act = rb.observations[rows, 0].copy(), rb.actions[rows, 0].copy()
            if hasattr(rb, "frame_arrays"):  # a FrameReplayBuffer: the rows' images with their state vectors
                obs = {**rb.store.get(rb.obs_frame[rows]), rb.state_key: obs}
        if not len(rows):
            return None
        q = critic_values(model, obs, act)
        big = np.abs(q).max(axis=1)
        worst = int(np.argmax(big))
        self.largest = max(self.largest, float(big[worst]))
        self.checks += 1
        self.seconds += time.perf_counter() - t0
        q_max = self.q_max(model.gamma)
        if not big[worst] > q_max:
            return None
        self.rollbacks += 1
        self.last = (f"|Q| {big[worst]:.4g} at stored row {int(rows[worst])} > Q_max {q_max:.4g} "
                     f"(= 2 x reward bound {self.reward_bound:g} / (1 - gamma {model.gamma:g}))")
        if self.rollbacks <= 10 or self.rollbacks % 100 == 0:
            log.warning("training iteration rolled back: the critic's %s on %d of %d rows beyond it; networks and "
                        "optimisers restored to before it (%d such rollbacks in this learner)", self.last,
                        int((big > q_max).sum()), len(rows), self.rollbacks)
        return self.last
