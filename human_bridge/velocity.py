"""Velocity control of P_h for people without a pointer: the logic the ``keyboard`` and ``gamepad`` clients share
(:mod:`khgrl.human_bridge.keyboard`, :mod:`khgrl.human_bridge.gamepad`). No Zenoh, no pygame: a device turns its
state into a :class:`Push`, and :class:`VelocityHold` turns pushes and the driven actor's frames into corrections.

A hold (docs/protocol.md, ``correction``): when the device's hold input goes down, P_h starts at the ``desired``
position of the driven actor's latest frame (projected onto the workspace box) and one ``active`` correction is
sent at once; every tick P_h moves by the pushed velocity times the tick's length (clipped to the workspace
box); while held, one ``active`` correction answers every frame of the driven actor (and one goes at least every
:data:`~khgrl.human_bridge.hold.KEEPALIVE_S` when no frame comes, e.g. the actor is paused: the hold every client
shares, :mod:`khgrl.human_bridge.hold`). The hold ends with one release when the hold
input goes up, on the episode's last frame (``last``; the hold input must then go up and down again to hold in
the next episode, as a mouse button must in the GUI), or when the client quits.

Axes: a :class:`Push` has three components in [-1, 1]: ``h`` moves the task's ``view_axes[0]`` (the main
view's horizontal), ``v`` its ``view_axes[1]`` (vertical) and ``d`` its ``view_third`` (ignored when the task
has none). At full push an axis moves at the client's speed: ``--speed`` command units per second, by default
:data:`DEFAULT_SPEED_FRACTION` of that axis's workspace span per second.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import Frame
from khgrl.human_bridge.hold import CorrectionHold

__all__ = ["Push", "VelocityHold", "axes_of", "dead_zone", "axis_speeds", "velocity", "DEFAULT_SPEED_FRACTION",
           "DEAD_ZONE", "MAX_DT"]

DEFAULT_SPEED_FRACTION = 0.1  # of each axis's workspace span per second, at full push
DEAD_ZONE = 0.15  # a stick deflection below this is no push
MAX_DT = 0.25  # a tick longer than this (a stalled loop) moves P_h as far as one of this length


@dataclass(frozen=True)
class Push:
    """What an input device asks for right now.

    :param hold: the hold input is down (intervene).
    :param h: push along the main view's horizontal axis (``view_axes[0]``), in [-1, 1].
    :param v: push along its vertical axis (``view_axes[1]``), in [-1, 1].
    :param d: push along the third axis (``view_third``), in [-1, 1].
    """

    hold: bool = False
    h: float = 0.0
    v: float = 0.0
    d: float = 0.0


def axes_of(task: TaskDescriptor) -> tuple[int, int, int | None]:
    """The outputs a push moves: (horizontal, vertical, third or None).

    :param task: the run's task.
    """
    return int(task.view_axes[0]), int(task.view_axes[1]), task.third


def dead_zone(value: float, zone: float = DEAD_ZONE) -> float:
    """A stick's deflection as a push: 0 inside ``zone``, beyond it rescaled to reach +-1 at full deflection.

    :param value: the deflection in [-1, 1] (values beyond are clipped).
    :param zone: the dead zone's half-width, in [0, 1).
    """
    x = float(np.clip(value, -1.0, 1.0))
    if abs(x) < zone:
        return 0.0
    return float(np.sign(x)) * (abs(x) - zone) / (1.0 - zone)


def axis_speeds(task: TaskDescriptor, speed: float | None = None) -> np.ndarray:
    """(O,) the speed of each output at full push, in command units per second.

    :param task: the run's task (its workspace box).
    :param speed: one speed for every axis (command units per second); None: :data:`DEFAULT_SPEED_FRACTION` of
        each axis's workspace span.
    """
    span = np.asarray(task.workspace_high, np.float64) - np.asarray(task.workspace_low, np.float64)
    if speed is None:
        return DEFAULT_SPEED_FRACTION * span
    if not np.isfinite(speed) or speed <= 0:
        raise ValueError(f"speed must be a positive number, not {speed!r}")
    return np.full(task.out_dim, float(speed))


def velocity(task: TaskDescriptor, push: Push, speeds: np.ndarray) -> np.ndarray:
    """(O,) the velocity of P_h under ``push``, in command units per second.

    :param task: the run's task (which outputs the push moves).
    :param push: the device's push (components clipped to [-1, 1]).
    :param speeds: (O,) each output's speed at full push (:func:`axis_speeds`).
    """
    out = np.zeros(task.out_dim)
    hx, vx, dx = axes_of(task)
    for axis, amount in ((hx, push.h), (vx, push.v), (dx, push.d)):
        if axis is not None:
            out[axis] += float(np.clip(amount, -1.0, 1.0)) * speeds[axis]
    return out


class VelocityHold(CorrectionHold):
    """Holds one actor's desired position P_h and moves it at the pushed velocity (see the module docstring); the
    hold itself (answers, keepalive, release) is :class:`~khgrl.human_bridge.hold.CorrectionHold`.

    :param task: the run's task (its size, axes and workspace box).
    :param send: ``send(actor, p_h or None, episode, t)`` publishes one correction
        (:meth:`khgrl.human_bridge.client.CorrectionPublisher.send`).
    :param actor: the actor to drive.
    :param speed: command units per second at full push (None: :data:`DEFAULT_SPEED_FRACTION` of each span).
    :param clock: the time source for the keepalive (seconds).
    """

    def __init__(self, task: TaskDescriptor, send: Callable, actor: str = "a0", speed: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(send, actor, clock)
        self.task = task
        self.low = np.asarray(task.workspace_low, np.float64)
        self.high = np.asarray(task.workspace_high, np.float64)
        self.speeds = axis_speeds(task, speed)
        self.ended = False  # the last hold ended with its episode: the hold input must go up first

    def offer(self, frame: Frame) -> bool:
        """A frame (see :meth:`CorrectionHold.offer`; frames of another size than the task's are ignored). A hold
        that ends with its episode needs the hold input to go up and down again."""
        if len(frame.desired) != self.task.out_dim:
            return False
        ended = super().offer(frame)
        self.ended = self.ended or ended
        return ended

    def update(self, push: Push, dt: float) -> None:
        """One tick of the device: start, move or end the hold.

        :param push: the device's state now.
        :param dt: seconds since the last tick (at most :data:`MAX_DT` of it counts).
        """
        if not push.hold:
            self.ended = False
            self.release()
            return
        if not self.holding:
            if not self.ended and self.frame is not None:  # start where the robot is told to be
                self.start(np.clip(np.asarray(self.frame.desired, np.float64), self.low, self.high))
            return
        step = velocity(self.task, push, self.speeds) * min(max(float(dt), 0.0), MAX_DT)
        self.move(np.clip(self.p_h + step, self.low, self.high))
        self.keepalive()
