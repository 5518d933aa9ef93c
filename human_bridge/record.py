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
from pathlib import Path

import numpy as np
from khgrl.human_bridge.strokes import Recorder

__all__ = ["record_task", "placeholder_demos", "record_loop", "add_parser", "run_record",
           "NO_DISPLAY_EXIT", "STRIP"]

NO_DISPLAY_EXIT = 3
STRIP = 80  # the text strip's height in pixels


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
