"""``khgrl human gui``: a pygame window in which a person watches an actor and drags its robot.

What it shows (rebuilt from the actor's ``frame`` messages; the static scene -- walls, gaps, obstacle, dashed
demonstrations, the red KMP mean, start and goal -- is rebuilt locally from the frame's scenario name with
``common.env.build_world``, exactly as the actor builds it):

* the exploration band the current L allows (from the actor's ``scale`` messages: its L table on the grid, or
  its scale model; without one, L is flat at the frame's ``scale``), the robot, its trail in the episode, the
  desired position P_t and the goal;
* a strip with actor, episode, step, return, the intervention state and a help line, and below it the L(s)
  curve with the current phase.

Input: press the left mouse button on the scene and drag: the desired position follows the pointer (P_h =
``SceneRenderer.pixel_to_world(pointer)``), sent as an ``active`` correction for every frame of the driven actor
(and at least every 100 ms) while the button is held; releasing sends ``active: false``. Keys: space pauses /
resumes the actors (``control/actor`` pause / resume), tab chooses the actor to drive, o toggles the overlays
(demonstrations, mean, band), q or Esc quits (releasing first).

``--screenshot FILE`` renders one frame offscreen (no display needed) after the first frame(s) arrived, or from a
synthetic frame with ``--offline``, writes a PNG and exits.

The window logic (:class:`GuiApp`) is separate from the Zenoh plumbing so tests can drive it with synthetic
pygame events; Zenoh callbacks only enqueue bytes (docs: zenoh-notes §5).
"""

from __future__ import annotations

import argparse
import logging
import os
import queue
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from common.protocol import Keys, ProtocolError, RejectCounter, decode, encode

__all__ = ["GuiApp", "ActorView", "run_gui", "add_parser", "synthetic_frames"]

log = logging.getLogger("khgrl.human.gui")

KEEPALIVE_S = 0.1  # while dragging, send at least this often even without frames
HELP = "drag: P_h  space: pause  tab: actor  o: overlays  q: quit"
CURVE_HEIGHT = 90
L_COLORS = ((31, 119, 180), (214, 39, 40))  # L_x, L_y


@dataclass
class ActorView:
    """What the GUI knows about one actor."""

    actor: str
    frame: dict | None = None
    trail: list = field(default_factory=list)
    table: np.ndarray | None = None  # (N, 2) L on the grid, from the actor's scale messages
    table_version: int = 0
    last_episode: dict | None = None  # stats of the last finished episode
    status: dict = field(default_factory=dict)
    frames: int = 0


class GuiApp:
    """The GUI's state machine: network input (``offer``), pygame events (``handle``), drawing (``draw``).

    Args:
        send: ``send(actor, p_h or None, episode, t)`` publishes one correction (``CorrectionPublisher.send``).
        control: ``control(command)`` publishes ``pause`` / ``resume`` to the actors.
        actor: the actor to drive (``*`` or None: the first that sends a frame).
    """

    def __init__(self, send: Callable, control: Callable | None = None, *, actor: str | None = None,
                 size: int = 600, strip_height: int = 80, client: str = "gui", run: str = "") -> None:
        self.send_fn = send
        self.control_fn = control
        self.want_actor = None if actor in (None, "", "*") else actor
        self.size = int(size)
        self.strip_height = int(strip_height)
        self.width = self.size
        self.height = self.size + self.strip_height + CURVE_HEIGHT
        self.client = client
        self.run = run
        self.actors: dict[str, ActorView] = {}
        self.current: str | None = self.want_actor
        self.dragging = False
        self.p_h: np.ndarray | None = None
        self.paused = False
        self.overlays = True
        self.quit = False
        self.sent = 0
        self.last_send = 0.0
        self.rejects = RejectCounter(f"human/{client}")
        self._worlds: dict[str, object] = {}
        self._renderers: dict[str, object] = {}
        self._band_cache: dict[tuple, np.ndarray] = {}

    # ------------------------------------------------------------------ network input
    def view(self, actor: str) -> ActorView:
        v = self.actors.get(actor)
        if v is None:
            v = self.actors[actor] = ActorView(actor)
            if self.current is None:
                self.current = actor
        return v

    def offer(self, kind: str, key: str, payload: bytes) -> None:
        """One message from the wire (already taken off the Zenoh callback's queue)."""
        try:
            msg = decode(kind, payload)
            if kind == "frame" and "ret" in msg:
                r = msg["ret"]
                if isinstance(r, bool) or not isinstance(r, (int, float)) or not np.isfinite(r):
                    raise ProtocolError("ret: not a finite number")
        except ProtocolError as exc:
            self.rejects.reject(kind, key, exc)
            return
        if kind == "status":
            actor = Keys.last_chunk(key, -1)
            if actor in self.actors and isinstance(msg["info"], dict):
                self.actors[actor].status = msg["info"]
            return
        v = self.view(msg["actor"])
        if kind == "frame":
            self.on_frame(v, msg)
        elif kind == "scale":
            self.on_scale(v, msg)
        elif kind == "episode":
            v.last_episode = msg["stats"]

    def on_frame(self, v: ActorView, f: dict) -> None:
        prev = v.frame
        if prev is None or prev["episode"] != f["episode"] or f["t"] < prev["t"]:
            v.trail = []
        v.trail.append(np.asarray(f["robot"], dtype=np.float64))
        if len(v.trail) > 2000:
            del v.trail[:1000]
        v.frame = f
        v.frames += 1
        if self.dragging and v.actor == self.current and self.p_h is not None:
            self._send(self.p_h)  # one correction per frame of the driven actor while held

    def on_scale(self, v: ActorView, msg: dict) -> None:
        table = msg.get("table")
        if table is None:
            try:
                from common.scale import ScaleModel

                sm = ScaleModel.from_dict(msg["model"])
                if sm.config.input == "phase" and v.frame is not None:
                    world = self.world(v.frame["scenario"])
                    table = sm.table(world.model.s[:, 0])
            except Exception as exc:  # noqa: BLE001 - a model we cannot use: fall back to the frame's scale
                self.rejects.reject("scale", v.actor, ProtocolError(f"model: {type(exc).__name__}: {exc}"))
                table = None
        if table is not None:
            table = np.asarray(table, dtype=np.float64)
            if table.ndim != 2 or table.shape[1] != 2 or not np.all(np.isfinite(table)) or np.any(table <= 0):
                self.rejects.reject("scale", v.actor, ProtocolError("table: not a positive (N, 2) array"))
                return
        v.table = table
        v.table_version += 1

    # ------------------------------------------------------------------ corrections
    def _frame_ids(self) -> tuple[int, int]:
        v = self.actors.get(self.current) if self.current else None
        if v is None or v.frame is None:
            return 0, 0
        return int(v.frame["episode"]), int(v.frame["t"])

    def _send(self, p_h) -> None:
        if self.current is None:
            return
        ep, t = self._frame_ids()
        self.send_fn(self.current, None if p_h is None else np.asarray(p_h, dtype=np.float64), ep, t)
        self.sent += 1
        self.last_send = time.monotonic()

    def press(self, pos) -> None:
        if self.current is None or pos[1] >= self.size:
            return
        self.dragging = True
        self.p_h = self.renderer_pixel_to_world(pos)
        self._send(self.p_h)

    def move(self, pos) -> None:
        if self.dragging:
            self.p_h = self.renderer_pixel_to_world(pos)

    def release(self) -> None:
        if self.dragging:
            self.dragging = False
            self.p_h = None
            self._send(None)

    def keepalive(self) -> None:
        """While held, re-send if no frame triggered a correction for KEEPALIVE_S (e.g. the actor paused)."""
        if self.dragging and self.p_h is not None and time.monotonic() - self.last_send >= KEEPALIVE_S:
            self._send(self.p_h)

    def renderer_pixel_to_world(self, pos) -> np.ndarray:
        span = float(self.size - 1)  # as SceneRenderer.pixel_to_world (same size): no world needed yet
        r = self._renderers.get(self._scenario()) if self._scenario() else None
        if r is not None:
            return np.asarray(r.pixel_to_world(np.asarray(pos, dtype=np.float64)), dtype=np.float64)
        return np.array([pos[0] / span, 1.0 - pos[1] / span])

    # ------------------------------------------------------------------ keys / events
    def handle(self, event) -> None:
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
            if event.key in (pygame.K_q, pygame.K_ESCAPE):
                self.stop()
            elif event.key == pygame.K_SPACE:
                self.toggle_pause()
            elif event.key == pygame.K_o:
                self.overlays = not self.overlays
            elif event.key == pygame.K_TAB:
                self.next_actor()

    def stop(self) -> None:
        self.release()
        self.quit = True

    def toggle_pause(self) -> None:
        self.paused = not self.paused
        if self.control_fn is not None:
            self.control_fn("pause" if self.paused else "resume")

    def next_actor(self) -> None:
        ids = sorted(self.actors)
        if not ids:
            return
        self.release()  # never keep dragging an actor we no longer watch
        i = ids.index(self.current) if self.current in ids else -1
        self.current = ids[(i + 1) % len(ids)]

    # ------------------------------------------------------------------ drawing
    def _scenario(self) -> str | None:
        v = self.actors.get(self.current) if self.current else None
        return v.frame["scenario"] if v is not None and v.frame is not None else None

    def world(self, scenario: str):
        w = self._worlds.get(scenario)
        if w is None:
            from common.env import build_world

            w = self._worlds[scenario] = build_world(scenario)
        return w

    def renderer(self, scenario: str):
        r = self._renderers.get(scenario)
        if r is None:
            from common.render import SceneRenderer

            w = self.world(scenario)
            r = self._renderers[scenario] = SceneRenderer(w.scenario, w.demos, np.asarray(w.model.grid_mean),
                                                          size=self.size, strip_height=self.strip_height)
        return r

    def scale_curve(self, v: ActorView) -> tuple[np.ndarray, np.ndarray]:
        """(phases (N,), L (N, 2)) of the actor: its L table, or flat at the frame's scale."""
        w = self.world(v.frame["scenario"])
        phases = np.asarray(w.model.s[:, 0], dtype=np.float64)
        if v.table is not None and len(v.table) == len(phases):
            return phases, v.table
        L = np.asarray(v.frame["scale"], dtype=np.float64)
        return phases, np.broadcast_to(L, (len(phases), 2))

    def band(self, v: ActorView) -> np.ndarray:
        w = self.world(v.frame["scenario"])
        _, L = self.scale_curve(v)
        key = (v.frame["scenario"], v.actor, v.table_version) if v.table is not None and len(v.table) == len(L) \
            else (v.frame["scenario"], "flat", tuple(np.round(L[0], 4)))
        band = self._band_cache.get(key)
        if band is None:
            half = np.einsum("nij,nj->ni", np.abs(w.model.grid_projector), L)
            mean = np.asarray(w.model.grid_mean)
            band = np.stack([mean - half, mean + half], axis=1)
            if len(self._band_cache) > 16:
                self._band_cache.clear()
            self._band_cache[key] = band
        return band

    def text(self, v: ActorView | None) -> list[str]:
        n = len(self.actors)
        if v is None or v.frame is None:
            return [f"waiting for frames on khgrl/{self.run}/actor/*/frame ...", HELP]
        f = v.frame
        ids = sorted(self.actors)
        ret = f"{f['ret']:.1f}" if "ret" in f else "-"
        last = v.last_episode
        last_s = f"  last ep {last.get('episode')}: {last.get('ret', 0.0):.1f}{' ok' if last.get('success') else ''}" \
            if last else ""
        line1 = (f"actor {v.actor} ({ids.index(v.actor) + 1}/{n})  episode {f['episode']}  step {f['t']}  "
                 f"return {ret}{last_s}")
        if self.dragging and self.p_h is not None:
            state = f"YOU DRAG  P_h=({self.p_h[0]:.3f}, {self.p_h[1]:.3f})"
        elif f["intervening"]:
            state = "intervention by another client"
        else:
            state = "no intervention"
        st = v.status.get("paused") if isinstance(v.status, dict) else None
        paused = self.paused if not isinstance(st, bool) else st
        line2 = f"{state}  |  {'PAUSED' if paused else 'running'}  |  sent {self.sent}" + \
            ("" if self.overlays else "  |  overlays off")
        return [line1, line2, HELP]

    def frame_state(self, v: ActorView):
        from common.render import FrameState

        f = v.frame
        return FrameState(
            robot=np.asarray(f["robot"]), desired=np.asarray(f["desired"]), phase=float(f["phase"]),
            trail=np.array(v.trail) if len(v.trail) >= 2 else None,
            band=self.band(v) if self.overlays else None,
            human_active=bool(f["intervening"]) or self.dragging,
            correction=self.p_h.copy() if self.dragging and self.p_h is not None else None,
            text=self.text(v))

    def draw(self, surface) -> None:
        import pygame

        from common.render import COLORS

        v = self.actors.get(self.current) if self.current else None
        if v is None or v.frame is None:
            surface.fill(COLORS["strip"])
            from common.render import _get_font

            font = _get_font(15)
            if font is not None:
                for i, line in enumerate(self.text(v)):
                    surface.blit(font.render(line, True, COLORS["text"]), (10, 10 + 20 * i))
            return
        r = self.renderer(v.frame["scenario"])
        r.draw(surface, self.frame_state(v), show_demos=self.overlays, show_mean=self.overlays, show_band=self.overlays)
        # the L(s) curve below the strip
        self.draw_curve(surface, pygame.Rect(0, self.size + self.strip_height, self.width, CURVE_HEIGHT), v)

    def draw_curve(self, surface, rect, v: ActorView) -> None:
        import pygame

        from common.render import COLORS, _get_font

        surface.fill((246, 246, 248), rect)
        pygame.draw.line(surface, COLORS["strip_line"], rect.topleft, (rect.right - 1, rect.top), 1)
        phases, L = self.scale_curve(v)
        font = _get_font(12)
        pad_l, pad_r, pad_t, pad_b = 54, 10, 16, 8
        plot = pygame.Rect(rect.left + pad_l, rect.top + pad_t, rect.width - pad_l - pad_r, rect.height - pad_t - pad_b)
        top = float(np.max(L)) * 1.1 if np.max(L) > 0 else 1.0
        pygame.draw.rect(surface, (255, 255, 255), plot)
        pygame.draw.rect(surface, COLORS["border"], plot, 1)
        for d in range(2):
            xs = plot.left + phases * (plot.width - 1)
            ys = plot.bottom - 1 - (L[:, d] / top) * (plot.height - 1)
            pts = np.c_[xs, ys]
            if len(pts) >= 2:
                pygame.draw.lines(surface, L_COLORS[d], False, pts, 2)
        s = float(np.clip(v.frame["phase"], 0.0, 1.0))
        x = plot.left + s * (plot.width - 1)
        pygame.draw.line(surface, COLORS["phase_bar"], (x, plot.top), (x, plot.bottom - 1), 1)
        if font is not None:
            src = "actor's L table" if v.table is not None else "flat at frame scale"
            cur = np.asarray(v.frame["scale"], dtype=np.float64)
            surface.blit(font.render(f"L(s) ({src})   now: L_x={cur[0]:.3g}  L_y={cur[1]:.3g}", True, COLORS["text"]),
                         (rect.left + 6, rect.top + 2))
            surface.blit(font.render(f"{top:.3g}", True, COLORS["text"]), (rect.left + 4, plot.top))
            surface.blit(font.render("0", True, COLORS["text"]), (rect.left + 4, plot.bottom - 12))
            for d, name in enumerate(("L_x", "L_y")):
                surface.blit(font.render(name, True, L_COLORS[d]), (rect.left + 4, plot.top + 18 + 14 * d))


# ------------------------------------------------------------------------------------ offline frames
def synthetic_frames(scenario: str, steps: int = 150, drag_from: int = 110, actor: str = "a0") -> list[dict]:
    """Frames like an actor's, from a local PassageEnv that follows the KMP mean (zero action) and is dragged
    above the mean from step ``drag_from`` on: for ``--offline`` screenshots and tests without a run."""
    from common.env import PassageEnv

    env = PassageEnv(scenario)
    env.reset()
    frames, ret = [], 0.0
    for k in range(steps):
        if k >= drag_from:
            m = env.mapping.mean(env.t)
            env.set_correction(np.array([m[0], m[1] + 0.08]))
        _, r, term, trunc, info = env.step(np.zeros(2))
        ret += r
        t = int(info["t"])
        frames.append({"v": 1, "kind": "frame", "sender": actor, "seq": k, "ts": time.time(), "actor": actor,
                       "episode": 1, "t": t, "phase": float(info["phase"]), "robot": env.robot.tolist(),
                       "desired": np.asarray(info["desired"]).tolist(), "mean": env.mapping.mean(t).tolist(),
                       "scale": np.asarray(info["scale"]).tolist(), "intervening": bool(info["intervened"]),
                       "scenario": scenario, "ret": float(ret)})
        if term or trunc:
            break
    return frames


# ------------------------------------------------------------------------------------ the process
def _offer_cb(q: queue.Queue, kind: str):
    def cb(sample) -> None:
        item = (kind, str(sample.key_expr), sample.payload.to_bytes())
        try:
            q.put_nowait(item)
        except queue.Full:  # drop the oldest: the GUI only needs the latest frames
            try:
                q.get_nowait()
            except queue.Empty:
                pass
            try:
                q.put_nowait(item)
            except queue.Full:
                pass

    return cb


class GuiSession:
    """Zenoh side of the GUI: subscriptions into a queue, a correction publisher, control puts."""

    def __init__(self, session, keys: Keys, client: str, actor: str | None, flag) -> None:
        import zenoh

        from human_bridge.service import CorrectionPublisher

        self.session = session
        self.keys = keys
        self.client = client
        self.flag = flag
        self.inbox: queue.Queue = queue.Queue(maxsize=4096)
        sel = "*" if actor in (None, "", "*") else actor
        self.subs = [
            session.declare_subscriber(keys.frame(sel), _offer_cb(self.inbox, "frame")),
            session.declare_subscriber(keys.scale(sel), _offer_cb(self.inbox, "scale")),
            session.declare_subscriber(keys.episode(sel), _offer_cb(self.inbox, "episode")),
            session.declare_subscriber(keys.status("actor", sel), _offer_cb(self.inbox, "status")),
            session.declare_subscriber(keys.control("human"), _offer_cb(self.inbox, "control")),
            session.declare_subscriber(keys.control("all"), _offer_cb(self.inbox, "control")),
        ]
        self.pub = CorrectionPublisher(session, keys, client)
        self.control_seq = 0
        self.token = session.liveliness().declare_token(keys.alive("human", client))
        self.status_pub = session.declare_publisher(keys.status("human", client),
                                                    congestion_control=zenoh.CongestionControl.DROP)
        self._t_status = time.monotonic()

    def send(self, actor: str, p_h, episode: int, t: int) -> None:
        self.pub.send(actor, p_h, episode, t)

    def control(self, command: str) -> None:
        import zenoh

        self.session.put(self.keys.control("actor"), encode("control", self.client, self.control_seq, command=command),
                         congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.INTERACTIVE_HIGH,
                         express=True)
        self.control_seq += 1

    def pump(self, app: GuiApp, limit: int = 2000) -> int:
        n = 0
        while n < limit:
            try:
                kind, key, payload = self.inbox.get_nowait()
            except queue.Empty:
                break
            n += 1
            if kind == "control":
                try:
                    if decode("control", payload)["command"] == "stop":
                        self.flag.set("stop command")
                except ProtocolError as exc:
                    app.rejects.reject("control", key, exc)
                continue
            app.offer(kind, key, payload)
        now = time.monotonic()
        if now - self._t_status >= 1.0:
            self._t_status = now
            self.status_pub.put(encode("status", self.client, int(now), role="human",
                                       info={"client": "gui", "corrections": self.pub.sent, "driving": app.current,
                                             "dragging": app.dragging, "rejects": app.rejects.by_kind()}))
        return n

    def close(self, app: GuiApp | None = None) -> None:
        try:
            for actor, active in list(self.pub.active.items()):
                if active:
                    self.pub.send(actor, None)
        finally:
            for d in [*self.subs, self.status_pub, self.token]:
                try:
                    d.undeclare()
                except Exception:  # noqa: BLE001
                    pass
            self.pub.close()


def _save_png(app: GuiApp, path: str) -> None:
    import pygame

    pygame.font.init()
    surf = pygame.Surface((app.width, app.height))
    app.draw(surf)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    pygame.image.save(surf, path)
    print(f"khgrl human gui: wrote {path} ({app.width}x{app.height})", flush=True)


def _offline_screenshot(args: argparse.Namespace) -> int:
    app = GuiApp(lambda *a: None, None, actor="a0", size=args.size, client=args.id, run=args.run or "offline")
    frames = synthetic_frames(args.scenario)
    for f in frames:
        app.offer("frame", "offline", encode("frame", "a0", f["seq"], **{k: f[k] for k in f if k not in
                                                                         ("v", "kind", "sender", "seq", "ts")}))
    last = frames[-1]
    if last["intervening"]:  # show the drag that produced the last frames
        app.dragging = True
        app.p_h = np.asarray(last["desired"])
    _save_png(app, args.screenshot)
    return 0


def run_gui(args: argparse.Namespace) -> int:
    from common.session import StopFlag, install_stop_handlers, open_client

    if args.screenshot:
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        if args.offline:
            return _offline_screenshot(args)
    if not args.run:
        print("khgrl human gui: --run is required (unless --screenshot with --offline)", flush=True)
        return 2
    import pygame

    keys = Keys(args.run)
    flag = StopFlag()
    install_stop_handlers(flag)
    with open_client(args.connect) as session:
        net = GuiSession(session, keys, args.id, args.actor, flag)
        app = GuiApp(net.send, net.control, actor=args.actor, size=args.size, client=args.id, run=args.run)
        try:
            if args.screenshot:
                return _screenshot_live(app, net, args, flag)
            pygame.display.init()
            pygame.font.init()
            screen = pygame.display.set_mode((app.width, app.height))
            pygame.display.set_caption(f"KhGRL human input ({args.id}) - run {args.run}")
            clock = pygame.time.Clock()
            print(f"khgrl human gui ({args.id}) on run {args.run}: drag the robot with the mouse", flush=True)
            while not flag and not app.quit:
                net.pump(app)
                for event in pygame.event.get():
                    app.handle(event)
                app.keepalive()
                app.draw(screen)
                pygame.display.flip()
                clock.tick(args.fps)
            app.release()
        finally:
            net.close(app)
            try:
                pygame.display.quit()
            except Exception:  # noqa: BLE001
                pass
    print(f"khgrl human gui: {app.sent} correction messages sent, {app.rejects.total} rejected", flush=True)
    return 0


def _screenshot_live(app: GuiApp, net: GuiSession, args: argparse.Namespace, flag) -> int:
    deadline = time.monotonic() + args.wait
    first = None
    seen_iv = counted = 0
    while not flag and time.monotonic() < deadline:
        net.pump(app)
        v = app.actors.get(app.current) if app.current else None
        if v is not None and v.frame is not None:
            first = first or time.monotonic()
            seen_iv = seen_iv + 1 if v.frame["intervening"] and v.frames > counted else seen_iv
            counted = v.frames
            if v.frames >= args.screenshot_frames or (args.screenshot_intervening and seen_iv >= args.screenshot_intervening):
                break
        time.sleep(0.01)
    if first is None:
        print(f"khgrl human gui: no frame within {args.wait} s", flush=True)
        return 1
    _save_png(app, args.screenshot)
    return 0


def add_parser(sub, default_endpoint: str) -> argparse.ArgumentParser:
    p = sub.add_parser("gui", help="a pygame window: watch an actor and drag its robot with the mouse")
    p.add_argument("--run", default=None, help="run id (key prefix khgrl/<run>/)")
    p.add_argument("--connect", default=default_endpoint, help="router endpoint (default %(default)s)")
    p.add_argument("--actor", default="*", help="actor id to drive first (default: the first seen; tab switches)")
    p.add_argument("--id", default="gui", help="client id")
    p.add_argument("--size", type=int, default=600, help="scene size in pixels")
    p.add_argument("--fps", type=float, default=60.0, help="window refresh rate")
    p.add_argument("--screenshot", default=None, metavar="FILE", help="render one frame to this PNG and exit")
    p.add_argument("--screenshot-frames", type=int, default=1, help="with --screenshot: frames to receive first")
    p.add_argument("--screenshot-intervening", type=int, default=0, metavar="N",
                   help="with --screenshot: take it at the N-th frame with an intervention (or after --screenshot-frames)")
    p.add_argument("--wait", type=float, default=120.0, help="with --screenshot: give up after this many seconds")
    p.add_argument("--offline", action="store_true", help="with --screenshot: a synthetic frame, no router needed")
    p.add_argument("--scenario", default="high_cov", choices=["high_cov", "low_cov"],
                   help="scenario of the --offline frame (a live GUI takes it from the frames)")
    # accepted so that `khgrl up --human gui` can pass the same arguments as to the scripted client
    p.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--episodes", type=int, nargs="+", default=None, help=argparse.SUPPRESS)
    p.add_argument("--run-dir", default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run_gui)
    return p
