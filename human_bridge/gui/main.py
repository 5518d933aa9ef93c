"""``khgrl human gui``: the window process -- a person watches an actor and drags its robot with the mouse.

Wiring, top to bottom: resolve the run settings; open the window (or fail loudly, exit code 3, when there is no
usable display); connect a :class:`~khgrl.human_bridge.client.HumanClient` that takes the actors' frames, scale models,
episode reports and status; ask the actors for the run's task (``task/actor/*``, a
:class:`~khgrl.common.wire.descriptor.TaskDescriptor`; asked again every :data:`TASK_RETRY_S` until one answers, the
window is then resized to the task's views); then, every display frame: hand the network's messages to the
:class:`GuiApp` (:class:`GuiSession`), the window's events to the app (which publishes corrections directly),
redraw (:class:`GuiView`).

``--screenshot FILE`` renders one frame offscreen after the first frame(s) arrived (or, with ``--offline``, from
synthetic frames of the run's task built here -- ``--task``/``--scenario`` -- no router needed), writes a PNG and
exits; it needs no display. A window needs one: a desktop
session (``DISPLAY`` or ``WAYLAND_DISPLAY``), or an explicit ``SDL_VIDEODRIVER`` (``dummy`` for a headless
window, as the tests use).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from khgrl.common.config.process import ProcessConfig
from khgrl.common.delivery.task_link import fetch_tasks
from khgrl.common.process import StopFlag, install_stop_handlers
from khgrl.common.tasks.scene_frame import frame_scene
from khgrl.common.wire.protocol import Frame
from khgrl.human_bridge.client import HumanClient, connected
from khgrl.human_bridge.gui.app import GuiApp, window_size
from khgrl.human_bridge.gui.view import GuiView

__all__ = ["GuiSession", "GUI_KINDS", "display_problem", "synthetic_frames", "add_arguments", "run", "NO_DISPLAY_EXIT",
           "TASK_RETRY_S"]

GUI_KINDS = ("frame", "scale", "episode", "status")
NO_DISPLAY_EXIT = 3
TASK_RETRY_S = 1.0  # while the task is unknown, ask the actors this often


class GuiSession:
    """The GUI's network side: a :class:`HumanClient` subscribed to what the window shows, feeding a
    :class:`GuiApp` whose corrections go straight to the client's publisher.

    :param link: the client (subscribed to :data:`GUI_KINDS`).
    """

    def __init__(self, link: HumanClient) -> None:
        self.link = link
        self._t_task = -TASK_RETRY_S

    def fetch_task(self, app: GuiApp, timeout: float = 0.3) -> bool:
        """Until ``app`` knows the run's task: ask the actors for it (at most every :data:`TASK_RETRY_S`, waiting
        up to ``timeout`` s for replies); True once the app has it."""
        if app.task is None and time.monotonic() - self._t_task >= TASK_RETRY_S:
            self._t_task = time.monotonic()
            found = fetch_tasks(self.link.session, self.link.keys, "actor", timeout, self.link.rejects)
            if found:
                app.set_task(found[sorted(found)[0]])
        return app.task is not None

    def app(self, **kw) -> GuiApp:
        """A :class:`GuiApp` that publishes with this client (``kw``: :class:`GuiApp`'s keyword arguments)."""
        return GuiApp(self.link.pub.send, self.link.control_actors, client=self.link.client,
                      rejects=self.link.rejects, **kw)

    def pump(self, app: GuiApp, limit: int = 2000) -> int:
        """Hand up to ``limit`` waiting messages to ``app``; publish the client's status now and then."""
        n = 0
        while n < limit and (got := self.link.next()) is not None:
            app.offer(got[1])
            n += 1
        self.link.publish_status()
        return n


def display_problem() -> str | None:
    """Why a window cannot be opened here (None: try). An explicit ``SDL_VIDEODRIVER`` is always tried."""
    if os.environ.get("SDL_VIDEODRIVER"):
        return None
    if sys.platform.startswith(("linux", "freebsd", "openbsd", "netbsd")) and not (
            os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return ("no display: DISPLAY and WAYLAND_DISPLAY are not set (run it in a desktop session, "
                "or set SDL_VIDEODRIVER=dummy for a headless window)")
    return None


def open_window(size: tuple[int, int], title: str):
    """The display surface; :class:`RuntimeError` with the reason when there is no usable display."""
    problem = display_problem()
    if problem:
        raise RuntimeError(problem)
    import pygame

    try:
        pygame.display.init()
        pygame.font.init()
        screen = pygame.display.set_mode(size)
    except pygame.error as exc:
        raise RuntimeError(f"SDL could not open a window: {exc}") from None
    pygame.display.set_caption(title)
    return screen


def window_loop(app: GuiApp, view: GuiView, net: GuiSession, screen, flag: StopFlag, fps: float) -> None:
    """Until quit or stopped: messages in, events in, keepalive, redraw."""
    import pygame

    clock = pygame.time.Clock()
    while not flag and not app.quit:
        if app.task is None and net.fetch_task(app):
            screen = pygame.display.set_mode((app.width, app.height))  # the task's views
        net.pump(app)
        for event in pygame.event.get():
            app.handle(event)
        app.keepalive()
        view.draw(screen)
        pygame.display.flip()
        clock.tick(fps)
    app.release()


def screenshot_live(app: GuiApp, view: GuiView, net: GuiSession, args: argparse.Namespace, flag: StopFlag) -> int:
    """Wait for ``--screenshot-frames`` frames (or the ``--screenshot-intervening``-th intervened one), save."""
    deadline = time.monotonic() + args.wait
    seen_iv = counted = 0
    while not flag and time.monotonic() < deadline:
        net.fetch_task(app)
        net.pump(app)
        v = app.driven
        if app.task is not None and v is not None and v.frame is not None:
            seen_iv += v.frame.intervening and v.frames > counted
            counted = v.frames
            if v.frames >= args.screenshot_frames or (args.screenshot_intervening
                                                      and seen_iv >= args.screenshot_intervening):
                view.save_png(args.screenshot)
                return 0
        time.sleep(0.01)
    if app.task is not None and app.driven is not None and app.driven.frame is not None:
        view.save_png(args.screenshot)
        return 0
    print(f"khgrl human gui: no {'frame' if app.task is not None else 'task'} within {args.wait} s", flush=True)
    return 1


def synthetic_frames(env, steps: int = 150, drag_from: int = 110, actor: str = "a0", lift: float = 0.08
                     ) -> list[Frame]:
    """Frames like an actor's, from a local :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` that follows the KMP mean
    (zero
    action) and is dragged ``lift`` (a fraction of the workspace) off the mean along the main view's vertical axis
    from step ``drag_from`` on: for ``--offline`` screenshots and tests without a run. A varying-scene task's first
    frame carries the episode's adapted KMP, as an actor's does."""
    o, up = env.world.out_dim, env.world.view.axes[1]
    offset = np.zeros(o)
    offset[up] = lift * float(env.world.high[up] - env.world.low[up])
    env.reset()
    frames, ret = [], 0.0
    for k in range(steps):
        if k >= drag_from:
            env.set_correction(env.mapping.mean(env.t) + offset)
        _, r, term, trunc, info = env.step(np.zeros(o))
        ret += r
        t = int(info["t"])
        frames.append(Frame(actor=actor, episode=1, t=t, phase=float(info["phase"]), robot=env.position.copy(),
                            desired=np.asarray(info["desired"]), mean=env.mapping.mean(t),
                            scale=np.asarray(info["scale"]), intervening=bool(info["intervened"]), task=env.task.name,
                            ret=float(ret), last=True if term or trunc else None,
                            **frame_scene(env, t, Frame.MAX_BYTES)))
        if term or trunc:
            break
    return frames


def offline_screenshot(args: argparse.Namespace, spec: str, demos: str = "") -> int:
    """``--screenshot FILE --offline``: the window drawn from synthetic frames of the task built here."""
    from khgrl.common.tasks.kgrl_env import KGRLEnv
    from khgrl.human_bridge.gui.task import local_descriptor, local_world

    world = local_world(spec, demos or None)
    app = GuiApp(lambda *a: None, None, actor="a0", task=local_descriptor(spec, world=world), size=args.size,
                 client=args.id, run="offline")
    frames = synthetic_frames(KGRLEnv(world=world))
    for f in frames:
        app.offer(f)
    if frames[-1].intervening:  # show the drag that produced the last frames
        app.hold.start(np.asarray(frames[-1].desired))
    GuiView(app).save_png(args.screenshot)
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The GUI's own flags."""
    parser.add_argument("--actor", default="*", help="actor id to drive first (default: the first seen; tab switches)")
    parser.add_argument("--id", default="gui", help="client id (default: %(default)s)")
    parser.add_argument("--size", type=int, default=600, help="scene size in pixels (default: %(default)s)")
    parser.add_argument("--fps", type=float, default=60.0, help="window refresh rate (default: %(default)s)")
    parser.add_argument("--screenshot", default=None, metavar="FILE",
                        help="render one frame to this PNG and exit (default: open the window)")
    parser.add_argument("--screenshot-frames", type=int, default=1,
                        help="with --screenshot: frames to receive first (default: %(default)s)")
    parser.add_argument("--screenshot-intervening", type=int, default=0, metavar="N",
                        help="with --screenshot: take it at the N-th frame with an intervention (or after "
                             "--screenshot-frames; default: %(default)s, none)")
    parser.add_argument("--wait", type=float, default=120.0,
                        help="with --screenshot: give up after this many seconds (default: %(default)s)")
    parser.add_argument("--offline", action="store_true",
                        help="with --screenshot: synthetic frames of the run's task (--task or --scenario) built "
                             "here, no router needed (default: off)")


def run(args: argparse.Namespace, proc: ProcessConfig) -> int:
    """``khgrl human gui``: exit 0 when the window is closed (or the run stops), 3 without a usable display.

    :param args: the parsed command line (:func:`add_arguments`).
    :param proc: the resolved run settings.
    """
    if args.offline and not args.screenshot:
        print("khgrl human gui: --offline needs --screenshot FILE", file=sys.stderr, flush=True)
        return 2
    if args.screenshot:
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # offscreen: no display needed
    if args.offline:
        from khgrl.common.tasks.api import TaskError

        try:
            return offline_screenshot(args, proc.cfg.task_spec, proc.cfg.demos)
        except TaskError as exc:
            print(f"khgrl human gui: {exc}", file=sys.stderr, flush=True)
            return 2
    import pygame

    try:
        screen = None if args.screenshot else open_window(window_size(args.size),
                                                          f"KhGRL human input ({args.id}) - run {proc.run}")
    except RuntimeError as exc:
        print(f"khgrl human gui: {exc}", file=sys.stderr, flush=True)
        return NO_DISPLAY_EXIT
    flag = StopFlag()
    install_stop_handlers(flag)
    try:
        with connected(proc, args.id, flag, args.actor, GUI_KINDS) as link:
            net = GuiSession(link)
            app = net.app(actor=args.actor, size=args.size, run=proc.run)
            view = GuiView(app)
            if args.screenshot:
                return screenshot_live(app, view, net, args, flag)
            print(f"khgrl human gui ({args.id}) on run {proc.run}: drag the robot with the mouse", flush=True)
            window_loop(app, view, net, screen, flag, args.fps)
    except ConnectionError as exc:
        if not flag:
            print(f"khgrl human gui: {exc}", file=sys.stderr, flush=True)
            return 1
        return 0
    finally:
        pygame.display.quit()
    print(f"khgrl human gui: {app.sent} correction messages sent, {app.rejects.total} rejected", flush=True)
    return 0
