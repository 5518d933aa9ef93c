"""Drawing the GUI (pygame): the task's views of the driven actor, a text strip, and the L(s) curves below.

The task's views are drawn by :class:`khgrl.common.tasks.render.TaskRenderer` from the run's task descriptor (the app's
``layout``): workspace, shapes, demonstrations, the red KMP mean; on top the exploration band the current L
allows (the actor's L table from its ``scale`` messages, or its scale model tabulated here; without either, L is
flat at the frame's ``scale``; the band from the descriptor's projector, :mod:`khgrl.human_bridge.gui.task`; for an
episode whose first frame brought its adapted KMP -- a varying scene, :class:`~khgrl.human_bridge.gui.app.EpisodeScene`
-- the mean, the band and the via-points of that episode),
the robot, its trail in the episode, the desired position and, while dragging, the person's P_h. The strip shows
actor, episode, step, return, the intervention state and a help line; below it, one L(s) curve per output.
"""

from __future__ import annotations

import os

import numpy as np
from khgrl.common.wire.protocol import ProtocolError
from khgrl.human_bridge.gui.app import CURVE_HEIGHT, HELP, ActorState, GuiApp
from khgrl.human_bridge.gui.task import band as task_band

__all__ = ["GuiView", "L_COLORS", "curve_color"]

L_COLORS = ((31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (140, 86, 75),
            (227, 119, 194), (127, 127, 127))
BAND_CACHE = 16
MAX_CURVE_LABELS = 4


def curve_color(d: int) -> tuple[int, int, int]:
    """The colour of output ``d``'s L curve."""
    return L_COLORS[d % len(L_COLORS)]


def _fmt(p: np.ndarray, k: int = 4) -> str:
    """A point as ``(a, b, ...)``, at most ``k`` values shown."""
    vals = ", ".join(f"{float(x):.3f}" for x in np.asarray(p).reshape(-1)[:k])
    return f"({vals}{', ...' if np.size(p) > k else ''})"


class GuiView:
    """Draws a :class:`GuiApp` (reads its state, never changes it).

    :param app: the GUI's state.
    """

    def __init__(self, app: GuiApp) -> None:
        self.app = app
        self._bands: dict[tuple, np.ndarray | None] = {}
        self._model_tables: dict[tuple, np.ndarray | None] = {}

    # ------------------------------------------------------------------ scene data
    @property
    def phases(self) -> np.ndarray:
        """(N,) the phases of the task's KMP grid."""
        return np.linspace(0.0, 1.0, self.app.task.horizon)

    def _table(self, v: ActorState, phases: np.ndarray) -> np.ndarray | None:
        """The actor's L on the grid: its table, or its (phase-input) scale model tabulated, or None."""
        if v.table is not None:
            return v.table if v.table.shape == (len(phases), self.app.task.out_dim) else None
        if v.model is None:
            return None
        key = (v.actor, v.scale_version)
        if key not in self._model_tables:
            self._model_tables[key] = None
            try:
                from khgrl.common.kmp.scale import ScaleModel

                sm = ScaleModel.from_dict(v.model)
                if sm.config.input == "phase":
                    table = np.asarray(sm.table(phases), dtype=np.float64)
                    if table.shape == (len(phases), self.app.task.out_dim):
                        self._model_tables[key] = table
            except Exception as exc:  # noqa: BLE001 - a model we cannot use: fall back to the frame's scale
                self.app.rejects.reject("scale", v.actor, ProtocolError(f"model: {type(exc).__name__}: {exc}"))
        return self._model_tables[key]

    def scale_curve(self, v: ActorState) -> tuple[np.ndarray, np.ndarray]:
        """(phases (N,), L (N, O)) of the actor: its L table, or flat at the frame's scale."""
        phases = self.phases
        table = self._table(v, phases)
        if table is not None:
            return phases, table
        scale = np.asarray(v.frame.scale, dtype=np.float64)
        return phases, np.broadcast_to(scale, (len(phases), len(scale)))

    def band(self, v: ActorState) -> np.ndarray | None:
        """(N, 2, O): the lower and upper edge of the exploration band on the KMP grid (None: no projector): about
        the episode's adapted mean with its projector when the actor's episode brought them, else the
        descriptor's."""
        phases, L = self.scale_curve(v)
        key = (v.actor, v.scale_version) if self._table(v, phases) is not None else \
            ("flat", tuple(np.round(L[0], 4)))
        scene = v.scene if v.scene is not None and v.scene.mean is not None else None
        if scene is not None:
            key = (*key, "scene", v.actor, v.scene_version)
        if key not in self._bands:
            if len(self._bands) > BAND_CACHE:
                self._bands.clear()
            self._bands[key] = task_band(self.app.task, L, None if scene is None else scene.mean,
                                         None if scene is None else scene.projector)
        return self._bands[key]

    # ------------------------------------------------------------------ text
    def text(self, v: ActorState | None) -> list[str]:
        """The strip's lines."""
        app = self.app
        if app.task is None:
            return [f"waiting for the run's task on khgrl/{app.run}/task/actor/* ...", HELP]
        if v is None or v.frame is None:
            return [f"task {app.task.name}: waiting for frames on khgrl/{app.run}/actor/*/frame ...", HELP]
        f = v.frame
        ids = sorted(app.actors)
        ret = "-" if f.ret is None else f"{f.ret:.1f}"
        last = v.last_episode
        last_s = f"  last ep {last.get('episode')}: {last.get('ret', 0.0):.1f}{' ok' if last.get('success') else ''}" \
            if last else ""
        line1 = (f"actor {v.actor} ({ids.index(v.actor) + 1}/{len(ids)})  episode {f.episode}  step {f.t}  "
                 f"return {ret}{last_s}")
        if app.dragging and app.p_h is not None:
            state = f"YOU DRAG  P_h={_fmt(app.p_h)}"
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
        """The renderer's input (a :class:`~khgrl.common.tasks.render.TaskFrame`) for the actor's latest frame."""
        from khgrl.common.tasks.render import TaskFrame

        app, f = self.app, v.frame
        return TaskFrame(position=np.asarray(f.robot), desired=np.asarray(f.desired), phase=float(f.phase), t=f.t,
                         trail=np.array(v.trail) if len(v.trail) >= 2 else None,
                         band=self.band(v) if app.overlays else None,
                         human_active=bool(f.intervening) or app.dragging,
                         correction=app.p_h.copy() if app.dragging and app.p_h is not None else None,
                         text=self.text(v), mean=None if v.scene is None else v.scene.mean,
                         via=None if v.scene is None else v.scene.via)

    def draw(self, surface) -> None:
        """The whole window: the views and strip of the driven actor, and its L(s) curves."""
        import pygame
        from khgrl.common.tasks.render_parts import COLORS, get_font

        app, v = self.app, self.app.driven
        if app.layout is None or v is None or v.frame is None:
            surface.fill(COLORS["strip"])
            font = get_font(15)
            if font is not None:
                for i, line in enumerate(self.text(v)):
                    surface.blit(font.render(line, True, COLORS["text"]), (10, 10 + 20 * i))
            return
        app.layout.draw(surface, self.frame_state(v), show_demos=app.overlays, show_mean=app.overlays,
                        show_band=app.overlays)
        self.draw_curve(surface, pygame.Rect(0, app.size + app.strip_height, app.width, CURVE_HEIGHT), v)

    def draw_curve(self, surface, rect, v: ActorState) -> None:
        """L_d(s) of every output d over the phase, with the current phase marked."""
        import pygame
        from khgrl.common.tasks.render_parts import COLORS, get_font

        surface.fill((246, 246, 248), rect)
        pygame.draw.line(surface, COLORS["strip_line"], rect.topleft, (rect.right - 1, rect.top), 1)
        phases, L = self.scale_curve(v)
        pad_l, pad_r, pad_t, pad_b = 54, 10, 16, 8
        plot = pygame.Rect(rect.left + pad_l, rect.top + pad_t, rect.width - pad_l - pad_r, rect.height - pad_t - pad_b)
        top = float(np.max(L)) * 1.1 if np.max(L) > 0 else 1.0
        pygame.draw.rect(surface, (255, 255, 255), plot)
        pygame.draw.rect(surface, COLORS["border"], plot, 1)
        for d in range(L.shape[1]):
            pts = np.c_[plot.left + phases * (plot.width - 1), plot.bottom - 1 - (L[:, d] / top) * (plot.height - 1)]
            if len(pts) >= 2:
                pygame.draw.lines(surface, curve_color(d), False, pts, 2)
        x = plot.left + float(np.clip(v.frame.phase, 0.0, 1.0)) * (plot.width - 1)
        pygame.draw.line(surface, COLORS["phase_bar"], (x, plot.top), (x, plot.bottom - 1), 1)
        font = get_font(12)
        if font is None:
            return
        names = self.app.task.axis_names
        src = "actor's L table" if self._table(v, phases) is not None else "flat at frame scale"
        cur = np.asarray(v.frame.scale, dtype=np.float64)
        now = "  ".join(f"L_{names[d]}={cur[d]:.3g}" for d in range(min(len(cur), MAX_CURVE_LABELS)))
        more = "  ..." if len(cur) > MAX_CURVE_LABELS else ""
        labels = [(f"L(s) ({src})   now: {now}{more}", COLORS["text"], (6, 2)),
                  (f"{top:.3g}", COLORS["text"], (4, plot.top - rect.top)),
                  ("0", COLORS["text"], (4, plot.bottom - 12 - rect.top))]
        labels += [(f"L_{names[d]}", curve_color(d), (4 + 25 * (d // 2), plot.top - rect.top + 16 + 14 * (d % 2)))
                   for d in range(min(L.shape[1], MAX_CURVE_LABELS))]
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
