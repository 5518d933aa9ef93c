"""``khgrl human keyboard``: correct an actor with the keyboard alone (no mouse), for any task.

A small pygame window (it needs the keyboard focus) shows the task, the driven actor (``--actor``, default
``a0``), whether you hold it and P_h. The keys (:class:`KeyboardInput`):

* **Space** (held) -- hold the robot: P_h starts at its desired position and the keys below move it;
  letting go of Space releases it. **Enter** toggles a hold instead (press once to hold, again to release),
  for people who cannot keep a key down.
* **Left / Right** -- move P_h along the main view's horizontal axis (the task's ``view_axes[0]``),
  **Up / Down** -- along its vertical axis (``view_axes[1]``),
  **PageUp / PageDown** (or **W / S**) -- along the third axis (``view_third``; 3-D tasks such as
  ``fetch:moved``: z).
* **q** or **Esc** -- quit (releasing first). Losing the window's focus releases too.

P_h moves at ``--speed`` command units per second (default: 10 % of each axis's workspace span per second) and
stays in the workspace box; the hold logic (one correction per frame, the release, the end of an episode) is
:class:`~khgrl.human_bridge.velocity.VelocityHold`. The window and the loop (:class:`PadClient`, :func:`run_pad`) are
shared with ``khgrl human gamepad`` (:mod:`khgrl.human_bridge.gamepad`). Without a usable display the client exits
with code 3 and one line (see :func:`khgrl.human_bridge.gui.main.display_problem`).

One module of ~330 lines on purpose: the keyboard and gamepad clients share one device loop; a device is one small
class.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Callable, Protocol

import numpy as np
from khgrl.common.config.process import ProcessConfig
from khgrl.common.process import StopFlag, install_stop_handlers
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import Frame
from khgrl.human_bridge.client import connected, fetch_task
from khgrl.human_bridge.gui.main import NO_DISPLAY_EXIT, open_window
from khgrl.human_bridge.velocity import Push, VelocityHold

__all__ = ["KeyboardInput", "PadClient", "Device", "quit_event", "run_pad", "window_loop", "positive", "add_arguments",
           "run", "WINDOW", "TASK_RETRY_S"]

WINDOW = (640, 170)
TASK_RETRY_S = 1.0  # while the task is unknown, ask the actors this often
HOLD_BG, FREE_BG, TEXT = (120, 30, 30), (30, 30, 40), (235, 235, 235)


class Device(Protocol):
    """An input device of a velocity client."""

    help: str

    def handle(self, event) -> bool:
        """Take one pygame event; True asks to quit."""

    def push(self) -> Push:
        """The device's state now."""


def estop_event(event) -> bool:
    """x pressed: the e-stop (every client's window; the actors hold until ``khgrl stop RUN_DIR --release``)."""
    import pygame

    return event.type == pygame.KEYDOWN and event.key == pygame.K_x


def ready_event(event) -> bool:
    """r pressed: the robot is ready for the next episode (``--confirm-reset``)."""
    import pygame

    return event.type == pygame.KEYDOWN and event.key == pygame.K_r


def quit_event(event) -> bool:
    """Window closed, q or Esc."""
    import pygame

    return event.type == pygame.QUIT or (event.type == pygame.KEYDOWN and event.key in (pygame.K_q, pygame.K_ESCAPE))


class KeyboardInput:
    """The keys held down, as a :class:`~khgrl.human_bridge.velocity.Push` (see the module docstring)."""

    help = "hold Space (Enter: toggle) + arrows, PageUp/PageDown or W/S to move P_h; q: quit"

    def __init__(self) -> None:
        self.down: set[int] = set()
        self.toggled = False

    def handle(self, event) -> bool:
        """Take one pygame event; True asks to quit.

        :param event: a pygame event (key down / up, focus lost, window closed).
        """
        import pygame

        if quit_event(event):
            return True
        if event.type == pygame.KEYDOWN:
            if event.key in (pygame.K_RETURN, pygame.K_KP_ENTER):
                self.toggled = not self.toggled
            else:
                self.down.add(event.key)
        elif event.type == pygame.KEYUP:
            self.down.discard(event.key)
        elif event.type == getattr(pygame, "WINDOWFOCUSLOST", -1):
            self.clear()
        return False

    def clear(self) -> None:
        """Forget every key and the toggle (the window lost the focus: its key-up events will not come)."""
        self.down.clear()
        self.toggled = False

    def _pair(self, plus: tuple[int, ...], minus: tuple[int, ...]) -> float:
        return float(any(k in self.down for k in plus)) - float(any(k in self.down for k in minus))

    def push(self) -> Push:
        """The keys' state now."""
        import pygame

        return Push(hold=pygame.K_SPACE in self.down or self.toggled,
                    h=self._pair((pygame.K_RIGHT,), (pygame.K_LEFT,)),
                    v=self._pair((pygame.K_UP,), (pygame.K_DOWN,)),
                    d=self._pair((pygame.K_PAGEUP, pygame.K_w), (pygame.K_PAGEDOWN, pygame.K_s)))


class PadClient:
    """A velocity client's window side: the run's task, the driven actor's frames in, the device's events in,
    corrections out (through ``link.pub``), its state as text.

    :param link: the client's network side (a :class:`~khgrl.human_bridge.client.HumanClient` subscribed to frames).
    :param device: the input device (:class:`Device`).
    :param actor: the actor to drive.
    :param speed: P_h's speed at full push in command units per second (None: 10 % of each span per second).
    :param name: the client's kind (``keyboard``, ``gamepad``), shown.
    :param run: the run id, shown.
    :param task: the run's task if known already (None: asked from the actors every :data:`TASK_RETRY_S`).
    :param events: returns the new pygame events (default ``pygame.event.get``): tests inject theirs here.
    """

    def __init__(self, link, device: Device, actor: str = "a0", speed: float | None = None, name: str = "keyboard",
                 run: str = "", task: TaskDescriptor | None = None, events: Callable[[], list] | None = None) -> None:
        self.link, self.device, self.actor, self.speed, self.name, self.run = link, device, actor, speed, name, run
        self.events = events
        self.task: TaskDescriptor | None = None
        self.hold: VelocityHold | None = None
        self.frame: Frame | None = None
        self.quit = False
        self.estopped = False  # x (or the device's e-stop button) was pressed
        self._t_task = -TASK_RETRY_S
        self._t_tick = time.monotonic()
        if task is not None:
            self.set_task(task)

    def set_task(self, task: TaskDescriptor) -> None:
        """The run's task: from now on the device drives a :class:`VelocityHold` in its workspace."""
        self.task = task
        self.hold = VelocityHold(task, self.link.pub.send, self.actor, self.speed)
        if self.frame is not None:
            self.hold.offer(self.frame)

    def fetch_task(self, timeout: float = 0.3) -> bool:
        """Until the task is known, ask the actors for it (at most every :data:`TASK_RETRY_S`); True once known."""
        if self.task is None and time.monotonic() - self._t_task >= TASK_RETRY_S:
            self._t_task = time.monotonic()
            found = fetch_task(self.link.session, self.link.keys, "actor", timeout=timeout,
                               stop=lambda: bool(self.link.flag))
            if found is not None:
                self.set_task(found)
        return self.task is not None

    def pump(self, limit: int = 2000) -> int:
        """Hand up to ``limit`` waiting frames to the hold; publish the client's status now and then."""
        n = 0
        while n < limit and (got := self.link.next()) is not None:
            n += 1
            msg = got[1]
            if isinstance(msg, Frame) and msg.actor == self.actor:
                self.frame = msg
                if self.hold is not None:
                    self.hold.offer(msg)
        self.link.publish_status()
        return n

    def step(self) -> None:
        """One pass of the loop: the task (until known), the network's frames, the device's events, the hold."""
        import pygame

        self.fetch_task()
        self.pump()
        for event in (self.events or pygame.event.get)():
            if estop_event(event) or getattr(self.device, "estop", lambda _: False)(event):
                self.press_estop()
            elif ready_event(event):
                self.link.control_actors("ready")
            if self.device.handle(event):
                self.stop()
        now = time.monotonic()
        dt, self._t_tick = now - self._t_tick, now
        if self.hold is not None and not self.quit:
            self.hold.update(self.device.push(), dt)

    def press_estop(self) -> None:
        """The e-stop: every actor this client is assigned to holds its robot (until the launcher releases it)."""
        self.estopped = True
        self.link.control_actors("estop")

    def stop(self) -> None:
        """Quit (releasing first)."""
        self.release()
        self.quit = True

    def release(self) -> None:
        """Release the driven actor if held."""
        if self.hold is not None:
            self.hold.release()

    def lines(self) -> list[str]:
        """The window's text: who, what task and frame, the hold's state, P_h (or the desired position), keys."""
        head = f"KhGRL human {self.name} ({self.link.client}) - run {self.run}"
        if self.task is None:
            return [head, "waiting for the run's task ...", "", "", self.device.help]
        names = self.task.axis_names
        f = self.frame
        where = f"episode {f.episode}  t {f.t}" if f is not None else "waiting for its frames ..."
        state = "HOLDING" if self.hold.holding else "free" + (
            " (the episode ended: let go and hold again)" if self.hold.ended else "")
        p = self.hold.p_h if self.hold.holding else (None if f is None else np.asarray(f.desired))
        label = "P_h" if self.hold.holding else "desired"
        vec = "" if p is None else f"{label}  " + "  ".join(f"{n} {x:.3f}" for n, x in zip(names, p))
        state += "  E-STOP pressed (khgrl stop RUN_DIR --release)" if self.estopped else ""
        return [head, f"task {self.task.name} (O = {self.task.out_dim})  actor {self.actor}  {where}",
                f"{state}  ({self.hold.sent} corrections sent)", vec, self.device.help + "; x: e-stop; r: ready"]

    def draw(self, surface) -> None:
        """Draw :meth:`lines` (the background turns red while holding)."""
        import pygame

        holding = self.hold is not None and self.hold.holding
        surface.fill(HOLD_BG if holding else FREE_BG)
        font = pygame.font.Font(None, 24)
        for i, line in enumerate(self.lines()):
            surface.blit(font.render(line, True, TEXT), (12, 10 + 30 * i))


def window_loop(client: PadClient, screen, flag: StopFlag, fps: float) -> None:
    """Until quit or stopped: step, draw; release on the way out.

    :param client: the window's client.
    :param screen: the display surface.
    :param flag: the process's stop flag.
    :param fps: passes per second.
    """
    import pygame

    clock = pygame.time.Clock()
    while not flag and not client.quit:
        client.step()
        client.draw(screen)
        pygame.display.flip()
        clock.tick(fps)
    client.release()


def run_pad(args: argparse.Namespace, proc: ProcessConfig, name: str, make_device: Callable[[], Device]) -> int:
    """A velocity client's process: the window (exit 3 without a display), the device (exit 3 when
    ``make_device`` raises :class:`RuntimeError`), the run's router, the loop; exit 0 when closed or stopped.

    :param args: the parsed command line (:func:`add_arguments` and the device's own flags).
    :param proc: the resolved run settings.
    :param name: the client's kind (``keyboard``, ``gamepad``).
    :param make_device: builds the input device once the window is open.
    """
    import pygame

    try:
        screen = open_window(WINDOW, f"KhGRL human {name} ({args.id}) - run {proc.run}")
        device = make_device()
    except RuntimeError as exc:
        print(f"khgrl human {name}: {exc}", file=sys.stderr, flush=True)
        pygame.quit()
        return NO_DISPLAY_EXIT
    flag = StopFlag()
    install_stop_handlers(flag)
    client = None
    try:
        with connected(proc, args.id, flag, args.actor, ("frame",)) as link:
            client = PadClient(link, device, actor=args.actor, speed=args.speed, name=name, run=proc.run)
            print(f"khgrl human {name} ({args.id}) on run {proc.run}, actor {args.actor}: {device.help}", flush=True)
            window_loop(client, screen, flag, args.fps)
    except ConnectionError as exc:
        if not flag:
            print(f"khgrl human {name}: {exc}", file=sys.stderr, flush=True)
            return 1
    finally:
        pygame.quit()
    sent = client.hold.sent if client is not None and client.hold is not None else 0
    print(f"khgrl human {name}: {sent} correction messages sent", flush=True)
    return 0


def positive(text: str) -> float:
    """argparse type: a positive finite number."""
    value = float(text)
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, not {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser, default_id: str = "keyboard") -> None:
    """The flags of a velocity client (``keyboard``; ``gamepad`` adds its own).

    :param parser: the client's sub-command parser.
    :param default_id: the default client id.
    """
    parser.add_argument("--actor", default="a0", help="the actor to drive (default: %(default)s)")
    parser.add_argument("--id", default=default_id, help="client id (default: %(default)s)")
    parser.add_argument("--speed", type=positive, default=None,
                        help="P_h's speed at full push, command units per second (default: 10%% of each axis's "
                             "workspace span per second)")
    parser.add_argument("--fps", type=float, default=60.0, help="window refresh rate (default: %(default)s)")


def run(args: argparse.Namespace, proc: ProcessConfig) -> int:
    """``khgrl human keyboard``: exit 0 when the window is closed (or the run stops), 3 without a display.

    :param args: the parsed command line (:func:`add_arguments`).
    :param proc: the resolved run settings.
    """
    return run_pad(args, proc, "keyboard", KeyboardInput)
