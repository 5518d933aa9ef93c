"""Delta position control: the action space of the HIL-SERL baseline (``--method hil-serl``).

HIL-SERL's policy commands a bounded end-effector displacement per step, clipped to a safety box (Luo et al.
2024, Section III-A; its Franka environments scale the action to a per-step step size and clip the pose to the
box). Here, with ``position`` the robot's measured position and a in [-1, 1]^O:

    P_t = clip(position + step (.) a, low, high)            (the workspace box: HIL-SERL's safety box)

There is no KMP band and no null space: the policy moves freely inside the box. The hard constraints G P >= c of
the LC-NS-KMP are not imposed -- the actor counts the steps that violate them (``violation_steps``).

Human takeover (HIL-SERL's intervention): the operator's P_h is mapped to the action that moves towards it,

    a_h = clip((P_h - position) (/) step, -1, 1),

which the robot executes and the transition stores (clipped components counted as for eq. 6).

The step size is one number for every axis (HIL-SERL scales the three translations alike): twice the largest
displacement between consecutive grid points of any demonstration, so that the demonstrations can be followed at
any phase and the policy can move twice as fast as the fastest one did.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DeltaControl", "STEP_FACTOR", "largest_step"]

STEP_FACTOR = 2.0  # step = STEP_FACTOR x the demonstrations' largest per-step displacement


def largest_step(demos: np.ndarray) -> float:
    """The demonstrations' largest per-axis displacement between consecutive grid points (the task's speed scale).

    :param demos: (M, N, O) demonstrations on the KMP grid.
    """
    d = np.asarray(demos, dtype=np.float64)
    largest = float(np.max(np.abs(np.diff(d, axis=1)))) if d.ndim == 3 and d.shape[1] > 1 else 0.0
    if not largest > 0.0:
        raise ValueError("the demonstrations do not move: no speed scale")
    return largest


@dataclass(frozen=True)
class DeltaControl:
    """Delta actions in the task's position space (see the module docstring).

    :param step: the largest displacement per step and axis (a positive number)
    :param low: the workspace box's lower corner, shape (O,)
    :param high: its upper corner, shape (O,)
    """

    step: float
    low: np.ndarray
    high: np.ndarray

    @classmethod
    def from_demos(cls, demos: np.ndarray, low: np.ndarray, high: np.ndarray) -> DeltaControl:
        """The step size from the demonstrations (M, N, O): :data:`STEP_FACTOR` times their largest per-axis
        displacement between consecutive grid points.

        :param demos: the demonstrations on the KMP grid
        :param low: the workspace's lower corner
        :param high: its upper corner
        """
        return cls(STEP_FACTOR * largest_step(demos), np.asarray(low, np.float64), np.asarray(high, np.float64))

    def act(self, position: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, bool]:
        """P_t for the policy's action: (the commanded position, whether the box clipped it).

        :param position: the robot's position now
        :param a: the action in [-1, 1]^O
        """
        target = np.asarray(position, np.float64) + self.step * np.asarray(a, np.float64)
        p = np.clip(target, self.low, self.high)
        return p, bool(np.any(p != target))

    def invert(self, position: np.ndarray, p_h: np.ndarray) -> tuple[np.ndarray, bool]:
        """The takeover action towards P_h: (a_h in [-1, 1]^O, whether a component was clipped).

        :param position: the robot's position now
        :param p_h: the human's desired position
        """
        raw = (np.asarray(p_h, np.float64) - np.asarray(position, np.float64)) / self.step
        a = np.clip(raw, -1.0, 1.0)
        return a, bool(np.any(a != raw))
