"""The GUI's state and input logic (no drawing, no network): the run's task, what it knows of each actor, and
what a person's mouse and keys do.

The task comes as a :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (:meth:`GuiApp.set_task`); its views' geometry
(:class:`~khgrl.common.tasks.render.TaskRenderer`: view 0 shows the task's two view axes, view 1, if the task has a
third axis, the first against the third) turns a pointer position into command coordinates. A drag in a view
sets that view's two coordinates of P_h; the others stay where the driven robot's desired position is when the
button goes down (so a 3-D task is corrected from its two views, one pair of axes at a time).

A drag: pressing the left button in a view sets the desired position P_h there and sends an ``active``
correction; while the button is held, one more for every frame of the driven actor (and at least every
:data:`~khgrl.human_bridge.hold.KEEPALIVE_S` when no frame comes, e.g. the actor is paused); releasing the button
sends the release. A live hold ends with its episode: on the episode's last frame (``last``) the GUI releases, and
the person presses again to correct the next episode. The hold is :class:`~khgrl.human_bridge.hold.CorrectionHold`,
the one every human client shares. Keys: space pauses / resumes the actors, x presses the e-stop (every actor holds
its robot until ``khgrl stop RUN_DIR --release``), tab chooses the
actor to drive, o toggles the overlays, q or Esc quits (releasing first).

Scenes that change every episode (issue 22): the first frame of an episode (t = 0) of a varying-scene task whose KMP
the actor adapted brings the episode's adapted mean, projector and via-points (``scene_*``, docs/protocol.md). The
GUI keeps them per actor (:class:`EpisodeScene`) for that episode and draws that mean, the band about it (under the
L in force) and the via-points; without them (a fixed scene, an actor that does not adapt, or a frame of another
episode) it draws the descriptor's, the demonstrations' mean and band. A GUI that joins in the middle of an
episode has missed its first frame: it shows the demonstrations' mean until the actor's next episode begins. A
scene whose grid or size is not the task's refuses the frame (counted, as a frame of another size is).

One module of ~370 lines on purpose: the window's one state machine (press, drag, release, keys, frames of
each actor); drawing is :mod:`~khgrl.human_bridge.gui.view`, sending :mod:`~khgrl.human_bridge.hold`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import ActorInfo
from khgrl.common.wire.protocol import (
    EpisodeReport,
    Frame,
    Message,
    ProtocolError,
    RejectCounter,
    Scale,
    Status,
    TaskInfo,
)
from khgrl.human_bridge.hold import CorrectionHold

__all__ = ["GuiApp", "ActorState", "EpisodeScene", "window_size", "CURVE_HEIGHT", "HELP"]

CURVE_HEIGHT = 90  # the L(s) curve below the text strip (pixels)
HELP = "drag: P_h  space: pause  x: e-stop  r: ready  tab: actor  o: overlays  q: quit"
TRAIL_MAX = 2000
PAUSE_RENEW_S = 20.0  # while paused, ask again this often (actors end a pause not renewed within human_pause_s)


def window_size(size: int, strip_height: int = 80, views: int = 1) -> tuple[int, int]:
    """(width, height) of the window: ``views`` scenes side by side, the text strip, the L(s) curve."""
    return int(size) * int(views), int(size) + int(strip_height) + CURVE_HEIGHT


@dataclass(frozen=True, eq=False)
class EpisodeScene:
    """One actor's episode scene, from the episode's first frame.

    :param episode: the episode it belongs to.
    :param mean: (N, O) the adapted KMP mean, or None (the frame did not carry it: a grid too long for a frame).
    :param projector: (N, O, O) its null-space projector, or None (the band is then the descriptor's projector
        about the adapted mean).
    :param via: (V, 1 + O) the via-points [phase, position...], or None.
    """

    episode: int
    mean: np.ndarray | None
    projector: np.ndarray | None
    via: np.ndarray | None


@dataclass
class ActorState:
    """What the GUI knows about one actor."""

    actor: str
    frame: Frame | None = None
    trail: list[np.ndarray] = field(default_factory=list)  # robot positions (O,) in the current episode
    table: np.ndarray | None = None  # (N, O) L on the KMP grid, from the actor's scale messages
    model: dict | None = None  # the actor's scale model, when its scale message has no table
    scale_version: int = 0  # counts scale messages (cache key of the drawn band)
    last_episode: dict | None = None  # stats of the last finished episode
    status: ActorInfo | None = None
    frames: int = 0
    scene: EpisodeScene | None = None  # the current episode's adapted KMP, if its first frame brought it
    scene_version: int = 0  # counts the scenes taken (cache key of the drawn band)


class GuiApp:
    """The GUI's state machine: messages in (:meth:`offer`), pygame events in (:meth:`handle`), corrections out.

    :param send: ``send(actor, p_h or None, episode, t)`` publishes one correction
        (:meth:`khgrl.human_bridge.client.CorrectionPublisher.send`).
    :param control: ``control(command)`` publishes ``pause`` / ``resume`` to the actors.
    :param actor: the actor to drive (``*`` or None: the first that sends a frame).
    :param task: the run's task (None: until :meth:`set_task`; frames are kept, nothing is drawn or dragged).
    :param size: the size of one view's scene in pixels.
    :param strip_height: the text strip's height in pixels.
    :param client: the client id (for the reject log).
    :param run: the run id (shown while waiting).
    :param rejects: where refused messages are counted (default: a counter of its own).
    """

    def __init__(self, send: Callable, control: Callable | None = None, *, actor: str | None = None,
                 task: TaskDescriptor | None = None, size: int = 600, strip_height: int = 80, client: str = "gui",
                 run: str = "", rejects: RejectCounter | None = None) -> None:
        self.send = send
        self.control = control
        self.hold = CorrectionHold(send, None if actor in (None, "", "*") else actor)
        self.size = int(size)
        self.strip_height = int(strip_height)
        self.width, self.height = window_size(size, strip_height)
        self.client = client
        self.run = run
        self.rejects = rejects if rejects is not None else RejectCounter(f"human/{client}")
        self.actors: dict[str, ActorState] = {}
        self.paused = False
        self.paused_at = 0.0  # when the pause was last asked for (time.monotonic(); renewed every PAUSE_RENEW_S)
        self.overlays = True
        self.quit = False
        self.task: TaskDescriptor | None = None
        self.layout = None  # the views' geometry (a TaskRenderer), with the task
        self.drag_view = 0  # the view the current drag started in
        if task is not None:
            self.set_task(task)

    def set_task(self, task: TaskDescriptor) -> None:
        """The run's task: lay out its views (the window is ``views`` scenes wide). A second, different task
        (another digest) is refused; frames of another size than the task's O are refused from now on."""
        if self.task is not None:
            if task.digest != self.task.digest:
                self.rejects.reject("task", task.name, ProtocolError(f"task {task.name!r} ({task.digest}) is not "
                                                                     f"the run's task {self.task.name!r}"))
            return
        from khgrl.common.tasks.render import TaskRenderer

        views = 1 if task.third is None else 2
        self.width, self.height = window_size(self.size, self.strip_height, views)
        self.layout = TaskRenderer(task, size=(self.width, self.size + self.strip_height),
                                   strip_height=self.strip_height, legend=True)
        self.task = task
        for v in self.actors.values():
            if v.frame is not None and len(v.frame.robot) != task.out_dim:
                v.frame, v.trail = None, []
            if v.scene is not None and self._scene_problem(v.scene.mean, v.scene.via) is not None:
                v.scene = None

    # ------------------------------------------------------------------ messages in
    def state(self, actor: str) -> ActorState:
        """The state of ``actor`` (created on its first message; the first actor seen is driven by default)."""
        v = self.actors.get(actor)
        if v is None:
            v = self.actors[actor] = ActorState(actor)
            if self.current is None:
                self.current = actor
        return v

    # ------------------------------------------------------------------ the hold (one CorrectionHold)
    @property
    def current(self) -> str | None:
        """The actor driven (its id), None before any."""
        return self.hold.actor

    @current.setter
    def current(self, actor: str | None) -> None:
        v = self.actors.get(actor) if actor else None
        self.hold.drive(actor, None if v is None else v.frame)  # releases the one held before

    @property
    def dragging(self) -> bool:
        """Whether the person holds the driven actor's P_h (button down)."""
        return self.hold.holding

    @property
    def p_h(self) -> np.ndarray | None:
        return self.hold.p_h

    @property
    def sent(self) -> int:
        return self.hold.sent

    @property
    def last_send(self) -> float:
        return self.hold.last_send

    @last_send.setter
    def last_send(self, value: float) -> None:
        self.hold.last_send = value

    @property
    def driven(self) -> ActorState | None:
        """The state of the driven actor, if it has sent anything."""
        return self.actors.get(self.current) if self.current else None

    def offer(self, msg: Message) -> None:
        """One decoded message from the wire.

        :param msg: a :class:`Frame`, :class:`Scale`, :class:`EpisodeReport`, an actor's :class:`Status` or a
            :class:`TaskInfo`.
        """
        if isinstance(msg, TaskInfo):
            self.set_task(msg.descriptor)
        elif isinstance(msg, Status):
            if isinstance(msg.info, ActorInfo) and msg.info.id in self.actors:
                self.actors[msg.info.id].status = msg.info
        elif isinstance(msg, Frame):
            if self._fits(msg.actor, "frame", len(msg.robot)) and self._scene_fits(msg):
                self.on_frame(self.state(msg.actor), msg)
        elif isinstance(msg, Scale):
            if msg.table is None or self._fits(msg.actor, "scale", msg.table.shape[1]):
                self.on_scale(self.state(msg.actor), msg)
        elif isinstance(msg, EpisodeReport):
            self.state(msg.actor).last_episode = msg.stats

    def _fits(self, actor: str, kind: str, o: int) -> bool:
        """Whether a message of ``o`` outputs fits the task (counted as refused if not)."""
        if self.task is None or o == self.task.out_dim:
            return True
        self.rejects.reject(kind, actor, ProtocolError(f"{o} outputs, the task {self.task.name!r} has "
                                                       f"{self.task.out_dim}"))
        return False

    def _scene_problem(self, mean: np.ndarray | None, via: np.ndarray | None) -> str | None:
        """Why a frame's scene does not fit the task (None: it fits, or the task is not known yet)."""
        if self.task is None:
            return None
        n, o = self.task.horizon, self.task.out_dim
        if mean is not None and mean.shape != (n, o):
            return f"scene_mean of shape {mean.shape}, the task {self.task.name!r} has ({n}, {o})"
        if via is not None and via.shape[1] != 1 + o:
            return f"scene_via of {via.shape[1]} columns, the task {self.task.name!r} has O = {o}"
        return None

    def _scene_fits(self, f: Frame) -> bool:
        """Whether a frame's scene fields (if any) fit the task's grid and outputs (counted as refused if not)."""
        why = self._scene_problem(f.scene_mean, f.scene_via) if f.has_scene else None
        if why is not None:
            self.rejects.reject("frame", f.actor, ProtocolError(why))
        return why is None

    def on_frame(self, v: ActorState, f: Frame) -> None:
        """A frame: extend the trail; keep the episode's scene (from its first frame; dropped with the episode);
        while dragging this actor, answer it (or release on its episode's last)."""
        prev = v.frame
        if prev is None or prev.episode != f.episode or f.t < prev.t:
            v.trail = []
        if f.has_scene:
            v.scene = EpisodeScene(f.episode, f.scene_mean, f.scene_projector, f.scene_via)
            v.scene_version += 1
        elif v.scene is not None and v.scene.episode != f.episode:
            v.scene = None
        v.trail.append(f.robot)
        if len(v.trail) > TRAIL_MAX:
            del v.trail[:TRAIL_MAX // 2]
        v.frame = f
        v.frames += 1
        self.hold.offer(f)  # while held, one correction per frame of the driven actor; released with its episode

    def on_scale(self, v: ActorState, msg: Scale) -> None:
        """A scale message: its L table (must be positive to be drawn), else its model for the view to tabulate."""
        if msg.table is not None and np.any(msg.table <= 0):
            self.rejects.reject("scale", v.actor, ProtocolError("table: L must be positive"))
            return
        v.table = None if msg.table is None else np.asarray(msg.table, dtype=np.float64)
        v.model = msg.model if msg.table is None else None
        v.scale_version += 1

    # ------------------------------------------------------------------ corrections out
    def point_at(self, pos, view: int | None = None, held: bool = True) -> np.ndarray | None:
        """P_h for the pointer at ``pos``: in ``view`` (default: the view under it, None if there is none), the
        view's two coordinates from the pointer, the others from the held P_h (if ``held``) or the driven robot's
        desired position (the KMP mean's start before any frame)."""
        if self.layout is None:
            return None
        if view is None:
            view = self.layout.view_at(pos)
            if view is None:
                return None
        v = self.driven
        base = self.p_h if held and self.p_h is not None else \
            (v.frame.desired if v is not None and v.frame is not None else self.task.mean[0])
        return self.layout.point_at(view, pos, base)

    def press(self, pos) -> None:
        """Left button down at ``pos``: start dragging (in a view only)."""
        if self.current is None or self.layout is None:
            return
        view = self.layout.view_at(pos)
        if view is None:
            return
        self.drag_view = view
        self.hold.start(self.point_at(pos, view, held=False))

    def move(self, pos) -> None:
        """The pointer moved: P_h follows it while dragging (sent with the next frame or keepalive)."""
        if self.dragging:
            self.hold.move(self.point_at(pos, self.drag_view))

    def release(self) -> None:
        """Let go (button up, focus lost, actor switched, episode ended, quit)."""
        self.hold.release()

    def keepalive(self) -> None:
        """While held, re-send if no frame triggered a correction lately (e.g. the actor paused); while paused,
        renew the pause every :data:`PAUSE_RENEW_S` (an actor ends a pause that is not renewed, ``human_pause_s``)."""
        self.hold.keepalive()
        if self.paused and self.control is not None and time.monotonic() - self.paused_at >= PAUSE_RENEW_S:
            self.paused_at = time.monotonic()
            self.control("pause")

    # ------------------------------------------------------------------ events
    def handle(self, event) -> None:
        """One pygame event."""
        import pygame

        if event.type == pygame.QUIT:
            self.stop()
        elif event.type == pygame.MOUSEBUTTONDOWN and event.button == 1:
            self.press(event.pos)
        elif event.type == pygame.MOUSEMOTION:
            self.move(event.pos)
        elif event.type == pygame.MOUSEBUTTONUP and event.button == 1:
            self.move(event.pos)
            self.release()
        elif event.type == getattr(pygame, "WINDOWFOCUSLOST", -1):
            self.release()
        elif event.type == pygame.KEYDOWN:
            self.key(event.key)

    def key(self, key: int) -> None:
        """A key press."""
        import pygame

        if key in (pygame.K_q, pygame.K_ESCAPE):
            self.stop()
        elif key == pygame.K_SPACE:
            self.toggle_pause()
        elif key == pygame.K_x and self.control is not None:  # the e-stop (released by the launcher only)
            self.control("estop")
        elif key == pygame.K_r and self.control is not None:  # the robot is ready for the next episode
            self.control("ready")
        elif key == pygame.K_o:
            self.overlays = not self.overlays
        elif key == pygame.K_TAB:
            self.next_actor()

    def stop(self) -> None:
        """Quit (releasing first)."""
        self.release()
        self.quit = True

    def toggle_pause(self) -> None:
        """Pause or resume the actors (``control/actor``)."""
        self.paused = not self.paused
        self.paused_at = time.monotonic()
        if self.control is not None:
            self.control("pause" if self.paused else "resume")

    def next_actor(self) -> None:
        """Drive the next actor (in id order), releasing the current one."""
        ids = sorted(self.actors)
        if not ids:
            return
        i = ids.index(self.current) if self.current in ids else -1
        self.current = ids[(i + 1) % len(ids)]  # releases the one dragged: never keep dragging an actor not watched
