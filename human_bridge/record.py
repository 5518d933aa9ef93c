"""``khgrl demos record``: draw demonstrations of a task with the mouse and save them as a demonstration file.

A window shows the task (its workspace, shapes, demonstrations and KMP mean, drawn by
:class:`khgrl.common.tasks.render.TaskRenderer` from a world built here: ``load_task(spec)`` + ``build_task_world``, no
Zenoh). Pressing the left button in a view starts a demonstration; while the button is held the pen -- the
pointer's position in that view's two axes, clipped to the workspace (with ``--speed``: trailing the pointer at
most that fast) -- is sampled ``--rate`` times a second with its time; releasing ends it. Each demonstration is
resampled in time to N steps (``--steps``, default the task's N), so all have the same length; the outputs the
view does not show are taken from the reference, the task's KMP mean resampled to N (a demonstration drawn in a
3-D task's main view follows the mean in the third axis). A task with no demonstrations yet (its file does not
exist) is shown with a placeholder: two straight lines from its ``start`` to its ``goal`` point.

Keys: BACKSPACE discards the last demonstration (or the one being drawn), ENTER or S keeps them and saves the
file (with ``--demos-per N``: saved when N are kept), ESC (or closing the window) quits without saving.
The file (.npz or .csv, :func:`khgrl.common.tasks.demos.save_demos`) is never overwritten unless ``--overwrite``.

Exit codes: 0 saved, 1 quit without saving, 2 bad arguments or task, 3 no usable display.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

__all__ = ["Recorder", "Stroke", "Layout", "resample", "record_task", "placeholder_demos", "record_loop", "add_parser",
           "run_record", "MIN_SAMPLES", "HELP", "NO_DISPLAY_EXIT", "STRIP"]

MIN_SAMPLES = 5  # a demonstration needs at least this many samples (a click is not one)
HELP = "press+drag: record   BACKSPACE: discard last   ENTER/S: save   ESC: quit"
NO_DISPLAY_EXIT = 3
STRIP = 80  # the text strip's height in pixels


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


# ---------------------------------------------------------------------------------------------- the task here
def placeholder_demos(task, n: int) -> np.ndarray:
    """Two straight lines from the task's ``start`` to its ``goal`` point (its view's shapes; default: across the
    workspace's diagonal), for a task with no demonstrations yet: the KMP fitted to them is the reference."""
    from khgrl.common.tasks.checks import vector

    low = vector(task, "workspace low", task.workspace[0])
    high = vector(task, "workspace high", task.workspace[1], low.size)
    at = {s.name.lower(): vector(task, f"shape {s.name!r}", s.at, low.size) for s in task.view.shapes
          if getattr(s, "kind", "") == "point"}
    a = at.get("start", low + 0.25 * (high - low))
    b = at.get("goal", low + 0.75 * (high - low))
    s = np.linspace(0.0, 1.0, int(n))[:, None]
    line = a + s * (b - a)
    return np.stack([line - 1e-3 * (high - low), line + 1e-3 * (high - low)])


@functools.lru_cache(maxsize=4)
def record_task(spec: str, steps: int | None = None):
    """(descriptor, placeholder) of ``spec`` built here (once per process); a task whose demonstrations cannot be
    loaded yet gets :func:`placeholder_demos` of ``steps`` (default 200) points (placeholder True).

    :raises khgrl.common.tasks.api.TaskError: naming what is wrong with the task.
    """
    from khgrl.common.tasks.api import TaskError, load_task, task_demos
    from khgrl.common.tasks.world import build_task_world
    from khgrl.human_bridge.gui.task import local_descriptor

    task = load_task(spec)
    try:
        task_demos(task)
        placeholder = False
    except TaskError:
        task = task.with_demos(placeholder_demos(task, steps or 200))
        placeholder = True
    return local_descriptor(spec, world=build_task_world(task)), placeholder


# ---------------------------------------------------------------------------------------------- the window
def draw(surface, renderer, rec: Recorder) -> None:
    """The task's views with the kept demonstrations (orange) and the one being drawn (the trail)."""
    import pygame
    from khgrl.common.tasks.render import TaskFrame

    cur = rec.current()
    pen = rec.reference[0] if cur is None else cur[-1]
    renderer.draw(surface, TaskFrame(position=pen, desired=pen, trail=cur, human_active=rec.stroke is not None,
                                     text=rec.text()), show_band=False)
    for k, v in enumerate(renderer.views):
        surface.set_clip(v.rect)
        for demo in rec.kept:
            pygame.draw.lines(surface, (235, 120, 20), False, renderer.to_pixel(k, demo), 2)
        surface.set_clip(None)


def record_loop(rec: Recorder, renderer, screen, fps: float = 60.0, clock=time.monotonic, events=None) -> None:
    """Until saved or quit: events in (stamped with ``clock()``), pen forward, redraw.

    :param events: returns this frame's pygame events (default: ``pygame.event.get``).
    """
    import pygame

    events = events or pygame.event.get
    ticker = pygame.time.Clock()
    while rec.done is None:
        now = clock()
        for event in events():
            rec.handle(event, now)
        rec.tick(now)
        draw(screen, renderer, rec)
        pygame.display.flip()
        ticker.tick(fps)


def add_parser(sub) -> argparse.ArgumentParser:
    """``record`` under ``khgrl demos`` (``sub``: the ``demos`` command's sub-parsers)."""
    p = sub.add_parser("record", help="draw demonstrations of a task with the mouse and save them (.npz/.csv)",
                       description=__doc__.split("\n\n")[1].replace("\n", " "))
    p.add_argument("--task", default="passage:high_cov",
                   help="the task: passage:SCENARIO or package.module:callable (default: %(default)s)")
    p.add_argument("--out", required=True, help="the demonstration file to write (.npz or .csv; required)")
    p.add_argument("--demos-per", type=int, default=0, metavar="N",
                   help="save and exit once N demonstrations are kept (default: 0, on ENTER or S)")
    p.add_argument("--steps", type=int, default=None, metavar="N",
                   help="resample every demonstration to N steps (default: the task's N)")
    p.add_argument("--rate", type=float, default=50.0, help="pen samples per second while drawing (default: "
                                                            "%(default)s)")
    p.add_argument("--speed", type=float, default=0.0,
                   help="the pen trails the pointer at most this fast, in workspace units per second, for smooth "
                        "demonstrations (default: %(default)s, follows the pointer)")
    p.add_argument("--size", type=int, default=600, help="size of one view in pixels (default: %(default)s)")
    p.add_argument("--fps", type=float, default=60.0, help="window refresh rate (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file (default: refuse)")
    p.set_defaults(func=run_record)
    return p


def _check_out(args: argparse.Namespace) -> Path:
    out = Path(args.out)
    if out.suffix not in (".npz", ".csv"):
        raise ValueError(f"--out {out}: use a .npz or .csv file")
    if out.exists() and not args.overwrite:
        raise ValueError(f"--out {out} exists (use --overwrite to replace it)")
    return out


def run_record(args: argparse.Namespace, *, clock=time.monotonic, events=None) -> int:
    """``khgrl demos record``: 0 saved, 1 quit without saving, 2 bad arguments or task, 3 no display.

    :param args: the parsed command line (:func:`add_parser`).
    :param clock: the time source of the samples (tests: a fake clock).
    :param events: the source of pygame events per frame (tests; default ``pygame.event.get``).
    """
    from khgrl.common.tasks.demos import save_demos
    from khgrl.human_bridge.gui.main import display_problem, open_window

    prog = "khgrl demos record"
    try:
        out = _check_out(args)
        problem = display_problem()
        if problem:
            print(f"{prog}: {problem}", file=sys.stderr, flush=True)
            return NO_DISPLAY_EXIT
        d, placeholder = record_task(args.task, args.steps)
        rec = Recorder(d.mean, d.workspace_low, d.workspace_high, None, steps=args.steps, rate=args.rate,
                       speed=args.speed, limit=args.demos_per)
    except ValueError as exc:  # TaskError and DemoFormatError too
        print(f"{prog}: {exc}", file=sys.stderr, flush=True)
        return 2
    from khgrl.common.tasks.render import TaskRenderer

    views = 1 if d.third is None else 2
    size = (int(args.size) * views, int(args.size) + STRIP)
    try:
        screen = open_window(size, f"KhGRL: record demonstrations of {d.name} -> {out.name}")
    except RuntimeError as exc:
        print(f"{prog}: {exc}", file=sys.stderr, flush=True)
        return NO_DISPLAY_EXIT
    rec.layout = renderer = TaskRenderer(d, size=size, strip_height=STRIP)
    if placeholder:
        rec.message = "(the task has no demonstrations yet: the straight line is a placeholder)"
    import pygame

    try:
        record_loop(rec, renderer, screen, args.fps, clock, events)
    finally:
        pygame.display.quit()
    if rec.done != "save":
        print(f"{prog}: quit, nothing saved ({len(rec.kept)} demonstrations dropped)", flush=True)
        return 1
    demos = rec.demos()
    try:
        out = _check_out(args)  # (it may have appeared meanwhile)
        save_demos(out, demos)
    except ValueError as exc:
        print(f"{prog}: {exc}", file=sys.stderr, flush=True)
        return 2
    m, n, o = demos.shape
    print(f"{prog}: wrote {m} demonstrations x {n} steps x {o} outputs of {d.name} to {out}", flush=True)
    if m < 2:
        print(f"{prog}: note: a task needs at least 2 demonstrations", flush=True)
    return 0
