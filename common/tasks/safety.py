"""Rate limits on the desired position P_t, between the KGRL mapping and the robot (``--rate-limit``;
:mod:`khgrl.common.config.safety`).

Per axis i, with ``v`` the last step of the position sent (P_{t-1} - P_{t-2}) and ``w = clip(P_t, low, high) -
P_{t-1}`` the step asked for (the mapping's or the human's P_t, brought into the workspace box):

    u_i = clip(w_i, -speed, speed)                          the speed limit
    u_i = clip(u_i, -b(|w_i|), b(|w_i|))                    slow down in time to stop at the target
    u_i = clip(u_i, v_i - accel, v_i + accel)               the acceleration limit
    P_sent = clip(P_{t-1} + u, low, high)                   the workspace box

with ``b(w)`` the largest step from which steps that shrink by ``accel`` each stop within ``w``: from a step
``u = (n + f) accel`` (``0 <= f < 1``) they cover ``S(u) = (n + 1) u - accel n (n + 1) / 2``, so ``b(w) = w / (n + 1) +
accel n / 2`` with ``n = floor((sqrt(1 + 8 w / accel) - 1) / 2)``. (``sqrt(2 accel w)``, the continuous braking
distance, passes the target by up to a step; ``u^2 + accel u = 2 accel w`` by up to ``accel / 8``.)

``speed`` and ``accel`` are the settings times ``d``, the demonstrations' largest per-axis step between consecutive
grid points (:func:`~khgrl.common.tasks.delta.largest_step`): the task's own speed scale. It is a rate limiter, not a
planner: the position sent lags the one asked for and may pass a target that stops suddenly by less than a braking
distance -- but never the box's edge, since the target is in the box and a braking distance always fits before the
edge once it did (moving towards an edge at ``u`` with ``D`` left, ``S(u) <= D``, and the next step keeps it:
``S(u) = u + S(u - accel)``). The box's own clip bites only from a start that could not stop in time (a path that
goes on at a velocity another limiter did not bound). A step whose position sent differs from the one asked for is
counted (``rate_limited``).
"""

from __future__ import annotations

import numpy as np
from khgrl.common.tasks.delta import largest_step

__all__ = ["RateLimiter"]


class RateLimiter:
    """Speed and acceleration limits on P_t, per axis (module docstring).

    :param speed: the largest step per control step (workspace units).
    :param accel: the largest change of the step from one control step to the next (0: none).
    :param low: the workspace's lower corner, (O,).
    :param high: its upper corner, (O,).
    """

    def __init__(self, speed: float, accel: float, low: np.ndarray, high: np.ndarray) -> None:
        if not speed > 0 or accel < 0:
            raise ValueError(f"a rate limiter needs speed > 0 and accel >= 0, got {speed}, {accel}")
        self.speed, self.accel = float(speed), float(accel)
        self.low, self.high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        self.last = np.clip(np.zeros_like(self.low), self.low, self.high)
        self.velocity = np.zeros_like(self.low)

    @classmethod
    def from_demos(cls, demos: np.ndarray, speed: float, accel: float, low: np.ndarray,
                   high: np.ndarray) -> RateLimiter:
        """Limits in units of the demonstrations' largest per-axis step.

        :param demos: (M, N, O) demonstrations on the KMP grid.
        :param speed: the speed limit in those units.
        :param accel: the acceleration limit in those units (0: none).
        :param low: the workspace's lower corner.
        :param high: its upper corner.
        """
        d = largest_step(demos)
        return cls(speed * d, accel * d, low, high)

    def reset(self, position: np.ndarray, velocity: np.ndarray | None = None) -> None:
        """Start again from ``position``: at rest (a new episode, or after any hold), or moving at ``velocity`` (the
        path back to the start, which goes on from the episode's last step and slows down within the limits).

        :param position: where the robot is, (O,).
        :param velocity: its last step, (O,) (None: at rest).
        """
        self.last = np.clip(np.asarray(position, np.float64), self.low, self.high)
        self.velocity = np.zeros_like(self.last) if velocity is None else np.asarray(velocity, np.float64).copy()

    def limit(self, desired: np.ndarray) -> tuple[np.ndarray, bool]:
        """The position to send for the one asked for: (P_sent, whether it differs from ``desired``).

        :param desired: P_t from the mapping or the human, (O,).
        """
        desired = np.asarray(desired, np.float64)
        want = np.clip(desired, self.low, self.high) - self.last
        u = np.clip(want, -self.speed, self.speed)
        if self.accel > 0:
            w, a = np.abs(want), self.accel
            n = np.floor(0.5 * (np.sqrt(1.0 + 8.0 * w / a) - 1.0))
            brake = w / (n + 1.0) + 0.5 * a * n
            u = np.clip(np.clip(u, -brake, brake), self.velocity - self.accel, self.velocity + self.accel)
        sent = np.clip(self.last + u, self.low, self.high)
        self.velocity, self.last = sent - self.last, sent
        return sent.copy(), bool(np.any(np.abs(sent - desired) > 1e-12))
