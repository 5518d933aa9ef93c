"""Drawing the GUI (pygame): the scene of the driven actor, a text strip, and the L(s) curve below it.

The static scene -- walls, gaps, obstacle, dashed demonstrations, the red KMP mean, start and goal -- is rebuilt
locally from the frame's scenario name with ``common.env.build_world``, exactly as the actor builds it. On top:
the exploration band the current L allows (the actor's L table from its ``scale`` messages, or its scale model
tabulated here; without either, L is flat at the frame's ``scale``), the robot, its trail in the episode, the
desired position and, while dragging, the person's P_h. The strip shows actor, episode, step, return, the
intervention state and a help line.
"""

from __future__ import annotations

import os

import numpy as np

from common.protocol import ProtocolError
from human_bridge.gui.app import CURVE_HEIGHT, HELP, ActorState, GuiApp

__all__ = ["GuiView", "L_COLORS"]

L_COLORS = ((31, 119, 180), (214, 39, 40))  # L_x, L_y
BAND_CACHE = 16


class GuiView:
    """Draws a :class:`GuiApp` (reads its state, never changes it).

    :param app: the GUI's state.
    """

    def __init__(self, app: GuiApp) -> None:
        self.app = app
        self._worlds: dict[str, object] = {}
        self._renderers: dict[str, object] = {}
        self._bands: dict[tuple, np.ndarray] = {}
        self._model_tables: dict[tuple, np.ndarray | None] = {}

    # ------------------------------------------------------------------ scene data
    def world(self, scenario: str):
        """The passage world of ``scenario`` (built once)."""
        w = self._worlds.get(scenario)
        if w is None:
            from common.env import build_world

            w = self._worlds[scenario] = build_world(scenario)
        return w

    def renderer(self, scenario: str):
        """The scene renderer of ``scenario`` at the app's size (built once)."""
        r = self._renderers.get(scenario)
        if r is None:
            from common.render import SceneRenderer

            w = self.world(scenario)
            r = self._renderers[scenario] = SceneRenderer(w.scenario, w.demos, np.asarray(w.model.grid_mean),
                                                          size=self.app.size, strip_height=self.app.strip_height)
        return r

    def _table(self, v: ActorState, phases: np.ndarray) -> np.ndarray | None:
        """The actor's L on the grid: its table, or its (phase-input) scale model tabulated, or None."""
        if v.table is not None:
            return v.table if len(v.table) == len(phases) else None
        if v.model is None:
            return None
        key = (v.actor, v.scale_version)
        if key not in self._model_tables:
            self._model_tables[key] = None
            try:
                from common.scale import ScaleModel

                sm = ScaleModel.from_dict(v.model)
                if sm.config.input == "phase":
                    self._model_tables[key] = np.asarray(sm.table(phases), dtype=np.float64)
            except Exception as exc:  # noqa: BLE001 - a model we cannot use: fall back to the frame's scale
                self.app.rejects.reject("scale", v.actor, ProtocolError(f"model: {type(exc).__name__}: {exc}"))
        return self._model_tables[key]

    def scale_curve(self, v: ActorState) -> tuple[np.ndarray, np.ndarray]:
        """(phases (N,), L (N, 2)) of the actor: its L table, or flat at the frame's scale."""
        phases = np.asarray(self.world(v.frame.scenario).model.s[:, 0], dtype=np.float64)
        table = self._table(v, phases)
        if table is not None:
            return phases, table
        return phases, np.broadcast_to(np.asarray(v.frame.scale, dtype=np.float64), (len(phases), 2))

    def band(self, v: ActorState) -> np.ndarray:
        """(N, 2, 2): the lower and upper edge of the exploration band on the KMP grid."""
        w = self.world(v.frame.scenario)
        phases, L = self.scale_curve(v)
        key = (v.frame.scenario, v.actor, v.scale_version) if self._table(v, phases) is not None else \
            (v.frame.scenario, "flat", tuple(np.round(L[0], 4)))
        band = self._bands.get(key)
        if band is None:
            half = np.einsum("nij,nj->ni", np.abs(w.model.grid_projector), L)
            mean = np.asarray(w.model.grid_mean)
            band = np.stack([mean - half, mean + half], axis=1)
            if len(self._bands) > BAND_CACHE:
                self._bands.clear()
            self._bands[key] = band
        return band

    # ------------------------------------------------------------------ text
    def text(self, v: ActorState | None) -> list[str]:
        """The strip's lines."""
        app = self.app
        if v is None or v.frame is None:
            return [f"waiting for frames on khgrl/{app.run}/actor/*/frame ...", HELP]
        f = v.frame
        ids = sorted(app.actors)
        ret = "-" if f.ret is None else f"{f.ret:.1f}"
        last = v.last_episode
        last_s = f"  last ep {last.get('episode')}: {last.get('ret', 0.0):.1f}{' ok' if last.get('success') else ''}" \
            if last else ""
        line1 = (f"actor {v.actor} ({ids.index(v.actor) + 1}/{len(ids)})  episode {f.episode}  step {f.t}  "
                 f"return {ret}{last_s}")
        if app.dragging and app.p_h is not None:
            state = f"YOU DRAG  P_h=({app.p_h[0]:.3f}, {app.p_h[1]:.3f})"
        elif f.intervening:
            state = "intervention by another client"
        else:
            state = "no intervention"
        paused = v.status.paused if v.status is not None else app.paused
        line2 = f"{state}  |  {'PAUSED' if paused else 'running'}  |  sent {app.sent}" + \
            ("" if app.overlays else "  |  overlays off")
        return [line1, line2, HELP]

    # ------------------------------------------------------------------ drawing
    def frame_state(self, v: ActorState):
        """The renderer's input for the actor's latest frame."""
        from common.render import FrameState

        app, f = self.app, v.frame
        return FrameState(robot=np.asarray(f.robot), desired=np.asarray(f.desired), phase=float(f.phase),
                          trail=np.array(v.trail) if len(v.trail) >= 2 else None,
                          band=self.band(v) if app.overlays else None,
                          human_active=bool(f.intervening) or app.dragging,
                          correction=app.p_h.copy() if app.dragging and app.p_h is not None else None,
                          text=self.text(v))

    def draw(self, surface) -> None:
        """The whole window: scene and strip of the driven actor, and its L(s) curve."""
        import pygame

        from common.render import COLORS, get_font

        app, v = self.app, self.app.driven
        if v is None or v.frame is None:
            surface.fill(COLORS["strip"])
            font = get_font(15)
            if font is not None:
                for i, line in enumerate(self.text(v)):
                    surface.blit(font.render(line, True, COLORS["text"]), (10, 10 + 20 * i))
            return
        r = self.renderer(v.frame.scenario)
        r.draw(surface, self.frame_state(v), show_demos=app.overlays, show_mean=app.overlays, show_band=app.overlays)
        self.draw_curve(surface, pygame.Rect(0, app.size + app.strip_height, app.width, CURVE_HEIGHT), v)

    def draw_curve(self, surface, rect, v: ActorState) -> None:
        """L_x(s) and L_y(s) over the phase, with the current phase marked."""
        import pygame

        from common.render import COLORS, get_font

        surface.fill((246, 246, 248), rect)
        pygame.draw.line(surface, COLORS["strip_line"], rect.topleft, (rect.right - 1, rect.top), 1)
        phases, L = self.scale_curve(v)
        pad_l, pad_r, pad_t, pad_b = 54, 10, 16, 8
        plot = pygame.Rect(rect.left + pad_l, rect.top + pad_t, rect.width - pad_l - pad_r, rect.height - pad_t - pad_b)
        top = float(np.max(L)) * 1.1 if np.max(L) > 0 else 1.0
        pygame.draw.rect(surface, (255, 255, 255), plot)
        pygame.draw.rect(surface, COLORS["border"], plot, 1)
        for d in range(2):
            pts = np.c_[plot.left + phases * (plot.width - 1), plot.bottom - 1 - (L[:, d] / top) * (plot.height - 1)]
            if len(pts) >= 2:
                pygame.draw.lines(surface, L_COLORS[d], False, pts, 2)
        x = plot.left + float(np.clip(v.frame.phase, 0.0, 1.0)) * (plot.width - 1)
        pygame.draw.line(surface, COLORS["phase_bar"], (x, plot.top), (x, plot.bottom - 1), 1)
        font = get_font(12)
        if font is None:
            return
        src = "actor's L table" if self._table(v, phases) is not None else "flat at frame scale"
        cur = np.asarray(v.frame.scale, dtype=np.float64)
        labels = [(f"L(s) ({src})   now: L_x={cur[0]:.3g}  L_y={cur[1]:.3g}", COLORS["text"], (6, 2)),
                  (f"{top:.3g}", COLORS["text"], (4, plot.top - rect.top)),
                  ("0", COLORS["text"], (4, plot.bottom - 12 - rect.top))]
        labels += [(name, L_COLORS[d], (4, plot.top - rect.top + 18 + 14 * d)) for d, name in enumerate(("L_x", "L_y"))]
        for label, color, (dx, dy) in labels:
            surface.blit(font.render(label, True, color), (rect.left + dx, rect.top + dy))

    def save_png(self, path: str) -> None:
        """Draw once onto an offscreen surface and write it as a PNG (no display needed)."""
        import pygame

        pygame.font.init()
        surf = pygame.Surface((self.app.width, self.app.height))
        self.draw(surf)
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        pygame.image.save(surf, path)
        print(f"khgrl human gui: wrote {path} ({self.app.width}x{self.app.height})", flush=True)
