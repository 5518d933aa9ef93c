"""The state of ``khgrl demos record`` (:mod:`khgrl.human_bridge.record`), without a window: pointer events and keys
in, demonstrations (M, N, O) out. A stroke is the pen's samples in one view's two axes with their times; a kept
stroke is resampled in time to N steps, and the outputs its view does not show follow the reference (the task's
KMP mean)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

__all__ = ["Recorder", "Stroke", "Layout", "resample", "MIN_SAMPLES", "HELP"]

MIN_SAMPLES = 5  # a demonstration needs at least this many samples (a click is not one)
HELP = "press+drag: record   BACKSPACE: discard last   ENTER/S: save   ESC: quit"


class Layout(Protocol):
    """The views' geometry (:class:`khgrl.common.tasks.render.TaskRenderer` has it)."""

    def view_at(self, pixel) -> int | None: ...

    def view_axes(self, view_index: int) -> tuple[int, int]: ...

    def to_world(self, view_index: int, pixel) -> tuple[float, float]: ...


def resample(values: np.ndarray, n: int, times: np.ndarray | None = None) -> np.ndarray:
    """``values`` (k, D) taken at ``times`` (k,) (default: equally spaced) as ``n`` samples equally spaced over
    the same time span, by linear interpolation.

    :param values: the samples, k >= 1.
    :param n: samples wanted (>= 2).
    :param times: increasing sample times (duplicates allowed: the later value wins).
    """
    values = np.asarray(values, dtype=np.float64)
    k = values.shape[0]
    if k == 1:
        return np.repeat(values, n, axis=0)
    t = np.linspace(0.0, 1.0, k) if times is None else np.asarray(times, dtype=np.float64)
    if times is not None:
        t = (t - t[0]) / (t[-1] - t[0]) if t[-1] > t[0] else np.linspace(0.0, 1.0, k)
    grid = np.linspace(0.0, 1.0, int(n))
    return np.stack([np.interp(grid, t, values[:, d]) for d in range(values.shape[1])], axis=1)


@dataclass
class Stroke:
    """One demonstration being drawn: the view it is drawn in and its pen samples with their times."""

    view: int
    axes: tuple[int, int]
    times: list[float] = field(default_factory=list)
    points: list[np.ndarray] = field(default_factory=list)  # (2,) values of ``axes``

    def add(self, now: float, p: np.ndarray) -> None:
        self.times.append(float(now))
        self.points.append(np.asarray(p, dtype=np.float64).copy())


class Recorder:
    """The recording's state (no drawing): pointer events and keys in, demonstrations (M, N, O) out.

    :param reference: (N0, O) the curve the unshown outputs follow (the task's KMP mean).
    :param low: (O,) the workspace box the pen is clipped to.
    :param high: (O,)
    :param layout: the views' geometry.
    :param steps: N, the length of every saved demonstration (default: N0).
    :param rate: pen samples per second while drawing.
    :param speed: the pen trails the pointer at most this fast (workspace units per second; 0: follows it).
    :param limit: save automatically once this many are kept (0: only on ENTER/S).
    """

    def __init__(self, reference: np.ndarray, low: np.ndarray, high: np.ndarray, layout: Layout, *,
                 steps: int | None = None, rate: float = 50.0, speed: float = 0.0, limit: int = 0) -> None:
        ref = np.asarray(reference, dtype=np.float64)
        self.steps = int(steps or ref.shape[0])
        if self.steps < 2 or rate <= 0 or speed < 0 or limit < 0:
            raise ValueError("need --steps >= 2, --rate > 0, --speed >= 0 and --demos-per >= 0")
        self.reference = resample(ref, self.steps)
        self.low, self.high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        self.layout = layout
        self.period = 1.0 / float(rate)
        self.speed = float(speed)
        self.limit = int(limit)
        self.kept: list[np.ndarray] = []  # (N, O) each
        self.stroke: Stroke | None = None
        self.pen: np.ndarray | None = None  # (2,) in the stroke's axes
        self.pointer: np.ndarray | None = None
        self.last_tick = 0.0
        self.done: str | None = None  # "save" or "quit"
        self.message = ""

    @property
    def out_dim(self) -> int:
        return int(self.reference.shape[1])

    # ------------------------------------------------------------------ pointer
    def _values(self, pos) -> np.ndarray:
        """The pointer's values in the stroke's axes, clipped to the workspace."""
        a = list(self.stroke.axes)
        return np.clip(np.asarray(self.layout.to_world(self.stroke.view, pos), np.float64), self.low[a], self.high[a])

    def press(self, pos, now: float) -> None:
        """Left button down: start a demonstration in the view under ``pos``."""
        view = self.layout.view_at(pos)
        if view is None or self.done is not None:
            return
        a, b = self.layout.view_axes(view)
        self.stroke = Stroke(view=int(view), axes=(int(a), int(b)))
        self.pointer = self._values(pos)
        self.pen = self.pointer.copy()
        self.stroke.add(now, self.pen)
        self.last_tick = now
        self.message = f"recording demonstration {len(self.kept) + 1} ..."

    def move(self, pos) -> None:
        """The pointer moved (outside the stroke's view the pen stays on the workspace's edge)."""
        if self.stroke is not None:
            self.pointer = self._values(pos)

    def tick(self, now: float) -> None:
        """Advance the pen toward the pointer and take a sample when a period has passed."""
        if self.stroke is None or self.pen is None or self.pointer is None:
            return
        dt, self.last_tick = max(0.0, now - self.last_tick), now
        step = self.pointer - self.pen
        dist = float(np.linalg.norm(step))
        if self.speed > 0 and dist > self.speed * dt:
            step = step * (self.speed * dt / dist)
        self.pen = self.pen + step
        if now - self.stroke.times[-1] >= self.period - 1e-9:
            self.stroke.add(now, self.pen)

    def release(self, pos, now: float) -> None:
        """Left button up: end the demonstration; keep it if it has enough samples."""
        if self.stroke is None:
            return
        self.move(pos)
        self.tick(now)
        if now > self.stroke.times[-1]:
            self.stroke.add(now, self.pen)
        stroke, self.stroke, self.pen, self.pointer = self.stroke, None, None, None
        if len(stroke.points) < MIN_SAMPLES:
            self.message = f"too short ({len(stroke.points)} samples, need {MIN_SAMPLES}): not kept"
            return
        self.kept.append(self.finish(stroke))
        self.message = f"kept demonstration {len(self.kept)}"
        if self.limit and len(self.kept) >= self.limit:
            self.done = "save"

    def finish(self, stroke: Stroke) -> np.ndarray:
        """A stroke as an (N, O) demonstration: its axes resampled in time, the others from the reference."""
        demo = self.reference.copy()
        demo[:, list(stroke.axes)] = resample(np.array(stroke.points), self.steps, np.array(stroke.times))
        return demo

    def current(self) -> np.ndarray | None:
        """(k, O) the demonstration being drawn so far (unshown outputs from the reference's start), or None."""
        if self.stroke is None or not self.stroke.points:
            return None
        pts = np.repeat(self.reference[:1], len(self.stroke.points), axis=0)
        pts[:, list(self.stroke.axes)] = np.array(self.stroke.points)
        return pts

    def demos(self) -> np.ndarray:
        """(M, N, O) the kept demonstrations."""
        return np.array(self.kept, dtype=np.float64).reshape(len(self.kept), self.steps, self.out_dim)

    # ------------------------------------------------------------------ keys and events
    def key(self, key: int) -> None:
        """BACKSPACE discards, ENTER/S saves, ESC quits."""
        import pygame

        if key == pygame.K_ESCAPE:
            self.done = "quit"
        elif key == pygame.K_BACKSPACE:
            if self.stroke is not None:
                self.stroke = self.pen = self.pointer = None
                self.message = "discarded the demonstration being drawn"
            elif self.kept:
                self.kept.pop()
                self.message = f"discarded the last demonstration ({len(self.kept)} kept)"
        elif key in (pygame.K_RETURN, pygame.K_KP_ENTER, pygame.K_s):
            if self.kept:
                self.done = "save"
            else:
                self.message = "nothing to save yet: draw a demonstration first"

    def handle(self, event, now: float) -> None:
        """One pygame event at time ``now``."""
        import pygame

        if event.type == pygame.QUIT:
            self.done = "quit"
        elif event.type == pygame.MOUSEBUTTONDOWN and event.button == 1:
            self.press(event.pos, now)
        elif event.type == pygame.MOUSEMOTION:
            self.move(event.pos)
        elif event.type == pygame.MOUSEBUTTONUP and event.button == 1:
            self.release(event.pos, now)
        elif event.type == pygame.KEYDOWN:
            self.key(event.key)

    def text(self) -> list[str]:
        """The window's text lines."""
        limit = f" of {self.limit}" if self.limit else ""
        return [f"{len(self.kept)}{limit} demonstrations kept, {self.steps} steps each", self.message, HELP]
