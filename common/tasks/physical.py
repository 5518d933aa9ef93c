"""Physical human-robot interaction detected from the robot's state (the paper's future work; README, "On a real
robot"): someone pushes the arm, and the actor takes where the arm is as the human's desired position P_h -- a
kinesthetic correction through the same eq. 6 as a drag.

Per control step, with P_t the position sent, x_{t-1} and x_t the measured positions before and after it,
``dev = x_t - P_t`` and ``v = x_t - x_{t-1}`` (infinity norms):

* an interaction **starts** after ``on_steps`` consecutive steps with ``|dev| > deviation``: the arm stays away from
  where it is sent by more than its controller's tracking error -- which is small only if P_t moves no faster than
  the arm can follow (``--rate-limit on`` with ``--max-speed`` at the arm's own speed);
* while it lasts, P_t is the arm's own position (the controller stops resisting), and it **ends** after
  ``off_steps`` consecutive steps with ``|v| <= motion``: the hand let go (or holds still; the policy takes over).

A push along the way the robot goes anyway leaves no deviation and is not seen (nor needs to be). A held object or a
surface the arm presses holds it back like a hand: while the task says the robot is in contact (``Task.contact``,
e.g. its gripper closed) no interaction starts -- a push then is not seen.
The thresholds are in units of the demonstrations' largest per-step displacement (the task's speed scale), as the
rate limits are (:mod:`khgrl.common.config.safety`). It uses positions only: no force sensor (a task whose robot
gives an external-force estimate could add it; none here does).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from khgrl.common.tasks.delta import largest_step

__all__ = ["PhysicalDetector", "DEVIATION", "MOTION", "ON_STEPS", "OFF_STEPS"]

DEVIATION, MOTION = 1.2, 0.25  # x the demonstrations' largest step (calibrated: docs/results_physical.md)
ON_STEPS, OFF_STEPS = 2, 3


@dataclass
class PhysicalDetector:
    """Starts and ends physical interactions from positions (module docstring).

    :param deviation: |x_t - P_t| above this (workspace units) starts one ...
    :param motion: ... and motion |x_t - x_{t-1}| at most this ends one.
    :param on_steps: consecutive steps that start one.
    :param off_steps: consecutive still steps that end one.
    """

    deviation: float
    motion: float
    on_steps: int = ON_STEPS
    off_steps: int = OFF_STEPS
    active: bool = False
    last: tuple[float, float] = (0.0, 0.0)  # the last step's |dev| and |v|, for the record
    _count: int = 0

    @classmethod
    def from_demos(cls, demos: np.ndarray) -> PhysicalDetector:
        """The default thresholds in units of the demonstrations' largest step.

        :param demos: (M, N, O) demonstrations.
        """
        d = largest_step(demos)
        return cls(DEVIATION * d, MOTION * d)

    def reset(self) -> None:
        """A new episode: no interaction."""
        self.active, self._count = False, 0

    def update(self, p_t: np.ndarray, before: np.ndarray, after: np.ndarray, contact: bool = False) -> bool:
        """One step: whether an interaction holds the arm after it.

        :param p_t: the position sent in this step.
        :param before: the measured position before it.
        :param after: the measured position after it.
        :param contact: the robot touches what it means to (the task's ``contact``): no interaction starts.
        """
        p_t, before, after = (np.asarray(a, np.float64) for a in (p_t, before, after))
        v = after - before
        self.last = (float(np.max(np.abs(after - p_t))), float(np.max(np.abs(v))))
        if self.active:
            still = self.last[1] <= self.motion
            self._count = self._count + 1 if still else 0
            if self._count >= self.off_steps:
                self.active, self._count = False, 0
            return self.active
        pushed = self.last[0] > self.deviation and not contact
        self._count = self._count + 1 if pushed else 0
        if self._count >= self.on_steps:
            self.active, self._count = True, 0
        return self.active
