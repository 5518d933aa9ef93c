"""pygame views of any task, drawn from its :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (GUI, monitors, GIFs).

``TaskRenderer(descriptor, size=(W, H))`` draws on offscreen surfaces only (no ``pygame.display``), so
:meth:`TaskRenderer.render_rgb` works headless. Layout: the views side by side on top, a text strip of
``strip_height`` pixels below. View 0 shows the descriptor's ``view_axes`` (i horizontal, j vertical); if the
descriptor has a third axis k, view 1 shows (i, k). Each view's axes are scaled to the workspace (widened to
the shapes and demonstrations that stick out of it, by at most a quarter of the workspace), with equal units
on both axes unless that would waste more than 3/4 of the view.

Static content (grid, ticks, workspace box, shapes, demonstrations in thin grey, the KMP mean in red) is
drawn once; the exploration band (which changes only with L) is composited into it and cached by its content.
A frame is then one blit plus the trail, the robot, the desired position P_t and the human's correction.

Scenes that change every episode (issue 22): a frame may bring its episode's adapted KMP mean and via-points
(:attr:`TaskFrame.mean`, :attr:`TaskFrame.via`; :func:`frame_from_env` takes them from a varying-scene env after
its reset): the red mean is then the adapted one, the via-points are marked (teal diamonds), and the static layers
are cached per scene. A frame without them draws the descriptor's mean, exactly as before.

Coordinates: :meth:`TaskRenderer.to_pixel` maps a point in command coordinates (O,) to pixel coordinates of
the renderer's own surface (x right, y down); :meth:`TaskRenderer.to_world` maps a pixel of a view back to
that view's two axis values; :meth:`TaskRenderer.view_at` says which view a pixel is in and
:meth:`TaskRenderer.point_at` completes a pixel to a full (O,) point. To draw at an offset, draw on a subsurface.

One module of ~380 lines on purpose: one class, the renderer's layout, caches and drawing order; its drawing
primitives are :mod:`~khgrl.common.tasks.render_parts`, a frame's content :mod:`~khgrl.common.tasks.render_frame`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pygame
from khgrl.common.tasks.render_frame import TaskFrame, frame_from_env
from khgrl.common.tasks.render_parts import (
    COLORS,
    SurfaceCache,
    band_key,
    band_layer,
    draw_legend,
    draw_via,
    get_font,
    nice_ticks,
    surface_rgb,
    view_extent,
)
from khgrl.common.wire.descriptor import TaskDescriptor

__all__ = ["TaskFrame", "TaskRenderer", "frame_from_env", "view_extent", "nice_ticks"]

_CACHE_SIZE = 8
_MARGIN = dict(left=46, right=12, top=10, bottom=32)  # plot rectangle inside a view's panel
_PANEL = (246, 246, 249)
_DEMO = COLORS["demo"] + (170,)
_SHAPE = {"box": (70, 70, 78, 200), "box_aside": (70, 70, 78, 45), "sphere": COLORS["obstacle"] + (170,)}
_POINTS = {"goal": COLORS["goal"], "start": COLORS["start"]}


@dataclass(frozen=True, eq=False)
class _Scene:
    mean: np.ndarray | None  # (N, O) the episode's adapted mean
    via: np.ndarray | None  # (V, 1 + O)
    key: tuple  # what the static layers are cached by


@dataclass(frozen=True, eq=False)
class _View:
    axes: tuple[int, int]  # command axes shown horizontally and vertically
    panel: pygame.Rect  # the view's part of the surface
    rect: pygame.Rect  # the plot area inside it
    lo: np.ndarray  # (2,) axis values at the plot's left / bottom edge
    hi: np.ndarray  # (2,) at the right / top edge


class TaskRenderer:
    """Draws a task's views (see the module docstring). No ``pygame.display`` calls.

    :param descriptor: the task.
    :param size: (W, H) of the whole image in pixels (views and strip).
    :param strip_height: pixels of the text strip at the bottom (0: none).
    :param equal_aspect: equal units on both axes of a view when the spans allow it.
    :param legend: a key (demonstrations, KMP mean, band, robot, P_t, P_h) in the top-left corner of view 0; the
        task's shapes carry their names in the views.
    """

    def __init__(self, descriptor: TaskDescriptor, size: tuple[int, int] = (800, 520), *, strip_height: int = 60,
                 equal_aspect: bool = True, legend: bool = False) -> None:
        w, h = (int(v) for v in size)
        n = 1 if descriptor.third is None else 2
        if w < 120 * n or h - strip_height < 100 or strip_height < 0:
            raise ValueError(f"size {size} with strip {strip_height} is too small for {n} view(s)")
        self.descriptor = descriptor
        self.width, self.height, self.strip_height = w, h, int(strip_height)
        self.mean = np.asarray(descriptor.mean, np.float64)
        self.demos = np.asarray(descriptor.demos, np.float64)
        lo, hi = view_extent(descriptor)
        pairs = [tuple(descriptor.view_axes)] + ([(descriptor.view_axes[0], descriptor.third)] if n == 2 else [])
        pw = w // n
        self.views: list[_View] = [self._layout(pygame.Rect(k * pw, 0, pw, h - strip_height), (a, b), lo, hi,
                                                equal_aspect) for k, (a, b) in enumerate(pairs)]
        self._static = SurfaceCache(_CACHE_SIZE)  # (show_demos, show_mean, scene key) -> (background, foreground)
        self._composites = SurfaceCache(_CACHE_SIZE)
        self._offscreen: pygame.Surface | None = None
        self._text: dict[tuple[int, str], pygame.Surface] = {}
        self._r = max(4, round(0.012 * min(v.rect.h for v in self.views)))
        self.legend = bool(legend)

    @staticmethod
    def _layout(panel: pygame.Rect, axes: tuple[int, int], lo: np.ndarray, hi: np.ndarray, equal: bool) -> _View:
        m = {k: min(v, panel.w // 5 if k in ("left", "right") else panel.h // 5) for k, v in _MARGIN.items()}
        rect = pygame.Rect(panel.left + m["left"], panel.top + m["top"], panel.w - m["left"] - m["right"],
                           panel.h - m["top"] - m["bottom"])
        vlo, vhi = lo[list(axes)].copy(), hi[list(axes)].copy()
        span = np.maximum(vhi - vlo, 1e-12)
        px = np.array([rect.w - 1, rect.h - 1], np.float64) / span  # pixels per unit
        if equal and px.max() / px.min() <= 4.0:
            mid, half = 0.5 * (vlo + vhi), 0.5 * np.array([rect.w - 1, rect.h - 1]) / px.min()
            vlo, vhi = mid - half, mid + half
        return _View(axes=axes, panel=panel, rect=rect, lo=vlo, hi=np.maximum(vhi, vlo + 1e-12))

    # ------------------------------------------------------------------ coordinates
    def _v2p(self, v: _View, q: np.ndarray) -> np.ndarray:
        """(..., 2) values of a view's two axes -> float pixels (clipped far outside, for pygame's ints)."""
        q = np.asarray(q, np.float64)
        f = (q - v.lo) / (v.hi - v.lo)
        out = np.empty(q.shape, np.float64)
        out[..., 0] = v.rect.left + f[..., 0] * (v.rect.w - 1)
        out[..., 1] = v.rect.top + (1.0 - f[..., 1]) * (v.rect.h - 1)
        lim = 8 * max(self.width, self.height)
        return np.clip(np.nan_to_num(out, nan=-lim), -lim, lim)

    def to_pixel(self, view_index: int, point: np.ndarray) -> np.ndarray:
        """(..., O) points in command coordinates -> (..., 2) float pixel coordinates in view ``view_index``."""
        v = self.views[view_index]
        return self._v2p(v, np.asarray(point, np.float64)[..., list(v.axes)])

    def to_world(self, view_index: int, pixel) -> tuple[float, float]:
        """A pixel (x, y) in view ``view_index`` -> the values of that view's two axes (inverse of to_pixel)."""
        v = self.views[view_index]
        x, y = (float(c) for c in pixel)
        fa = (x - v.rect.left) / (v.rect.w - 1)
        fb = 1.0 - (y - v.rect.top) / (v.rect.h - 1)
        return (float(v.lo[0] + fa * (v.hi[0] - v.lo[0])), float(v.lo[1] + fb * (v.hi[1] - v.lo[1])))

    def view_at(self, pixel) -> int | None:
        """The index of the view whose plot area holds ``pixel``, or None."""
        x, y = (int(round(float(c))) for c in pixel)
        return next((k for k, v in enumerate(self.views) if v.rect.collidepoint(x, y)), None)

    def view_axes(self, view_index: int) -> tuple[int, int]:
        """The command axes (horizontal, vertical) of view ``view_index``."""
        return self.views[view_index].axes

    def point_at(self, view_index: int, pixel, base: np.ndarray) -> np.ndarray:
        """``base`` (O,) with the two coordinates of view ``view_index`` taken from ``pixel``."""
        out = np.array(base, dtype=np.float64).reshape(-1).copy()
        a, b = self.views[view_index].axes
        out[a], out[b] = self.to_world(view_index, pixel)
        return out

    # ------------------------------------------------------------------ static layers
    def _static_layers(self, show_demos: bool, show_mean: bool, scene: _Scene | None = None
                       ) -> tuple[pygame.Surface, pygame.Surface]:
        key = (show_demos, show_mean, None if scene is None else scene.key)
        got = self._static.get(key)
        if got is not None:
            return got
        size = (self.width, self.height - self.strip_height)
        bg, fg = pygame.Surface(size), pygame.Surface(size, pygame.SRCALPHA)
        bg.fill(_PANEL)
        fg.fill((0, 0, 0, 0))
        for k, v in enumerate(self.views):
            self._draw_axes(bg, v)
            fg.set_clip(v.rect)
            self._draw_content(fg, k, show_demos, show_mean, scene)
            fg.set_clip(None)
        if self.legend:
            adapted = scene is not None and scene.mean is not None
            entries = [("demo", "demonstrations")] * show_demos + \
                [("mean", "KMP mean (adapted)" if adapted else "KMP mean")] * show_mean + \
                [("via", "via-point")] * (show_mean and scene is not None and scene.via is not None) + [
                ("band", "exploration band"), ("robot", "robot"), ("desired", "desired P_t"),
                ("correction", "human P_h")]
            fg.set_clip(self.views[0].rect)
            draw_legend(fg, (self.views[0].rect.left + 6, self.views[0].rect.top + 6), entries)
            fg.set_clip(None)
        return self._static.put(key, (bg, fg))

    def _draw_axes(self, bg: pygame.Surface, v: _View) -> None:
        """Plot background, grid at round values, tick labels, axis names."""
        pygame.draw.rect(bg, COLORS["background"], v.rect)
        font, names = get_font(11), self.descriptor.axis_names
        for dim in (0, 1):
            for val in nice_ticks(v.lo[dim], v.hi[dim]):
                q = np.array([val, v.lo[1]]) if dim == 0 else np.array([v.lo[0], val])
                x, y = (int(round(c)) for c in self._v2p(v, q))
                if dim == 0:
                    pygame.draw.line(bg, COLORS["grid"], (x, v.rect.top), (x, v.rect.bottom - 1))
                else:
                    pygame.draw.line(bg, COLORS["grid"], (v.rect.left, y), (v.rect.right - 1, y))
                if font is not None:
                    img = font.render(f"{val + 0.0:g}", True, COLORS["text"])  # no "-0"
                    pos = (x - img.get_width() // 2, v.rect.bottom + 2) if dim == 0 else \
                        (v.rect.left - img.get_width() - 3, y - img.get_height() // 2)
                    bg.blit(img, pos)
        pygame.draw.rect(bg, COLORS["border"], v.rect, 1)
        font = get_font(13)
        if font is not None:
            a, b = (font.render(names[k], True, COLORS["text"]) for k in v.axes)
            bg.blit(a, (v.rect.centerx - a.get_width() // 2, v.panel.bottom - a.get_height() - 1))
            b = pygame.transform.rotate(b, 90)
            bg.blit(b, (v.panel.left + 1, v.rect.centery - b.get_height() // 2))

    def _draw_content(self, fg: pygame.Surface, k: int, show_demos: bool, show_mean: bool,
                      scene: _Scene | None = None) -> None:
        """Workspace box, shapes, demonstrations, the KMP mean (the episode's, if ``scene`` has one) and the
        scene's via-points of view k."""
        d, v = self.descriptor, self.views[k]
        a, b = v.axes
        lo = self._v2p(v, np.array([d.workspace_low[a], d.workspace_high[b]]))
        hi = self._v2p(v, np.array([d.workspace_high[a], d.workspace_low[b]]))
        pygame.draw.rect(fg, COLORS["border"] + (255,), pygame.Rect(lo[0], lo[1], hi[0] - lo[0] + 1,
                                                                   hi[1] - lo[1] + 1), 1)
        for s in sorted((s for s in d.shapes if s["kind"] != "point"), key=lambda s: s["kind"] != "box"):
            self._draw_shape(fg, v, s)  # boxes first: a sphere on a table stays visible
        if show_demos:
            for demo in self.demos:
                pygame.draw.aalines(fg, _DEMO, False, self.to_pixel(k, demo))
        mean = self.mean if scene is None or scene.mean is None else scene.mean
        if show_mean and len(mean) >= 2:
            pts = self.to_pixel(k, mean)
            pygame.draw.lines(fg, COLORS["mean"] + (255,), False, pts, 2)
            pygame.draw.aalines(fg, COLORS["mean"] + (255,), False, pts)
        if show_mean and scene is not None and scene.via is not None:
            for x, y in self.to_pixel(k, scene.via[:, 1:]):
                draw_via(fg, (x, y), 7)
        for s in d.shapes:
            if s["kind"] == "point":
                self._draw_shape(fg, v, s)

    def _aside(self, v: _View, box: dict) -> bool:
        """Whether ``box`` lies wholly beside the demonstrations along an axis the view does not show (a table
        under the whole task seen from above): drawn faintly, so that it does not hide what is drawn over it."""
        demos = np.asarray(self.descriptor.demos, np.float64).reshape(-1, self.descriptor.out_dim)
        for c in set(range(self.descriptor.out_dim)) - set(v.axes):
            if box["high"][c] <= demos[:, c].min() or box["low"][c] >= demos[:, c].max():
                return True
        return False

    def _draw_shape(self, fg: pygame.Surface, v: _View, s: dict) -> None:
        a, b = v.axes
        font = get_font(11)
        if s["kind"] == "box":
            p0 = self._v2p(v, np.array([s["low"][a], s["high"][b]]))
            p1 = self._v2p(v, np.array([s["high"][a], s["low"][b]]))
            rect = pygame.Rect(round(p0[0]), round(p0[1]), max(1, round(p1[0] - p0[0])), max(1, round(p1[1] - p0[1])))
            pygame.draw.rect(fg, _SHAPE["box_aside"] if self._aside(v, s) else _SHAPE["box"], rect)
            label_at = (rect.left + 2, rect.top + 1) if font and font.size(s["name"])[0] < rect.w - 4 else None
        elif s["kind"] == "sphere":
            c = np.asarray(s["center"], np.float64)[[a, b]]
            p0 = self._v2p(v, c - s["radius"])
            p1 = self._v2p(v, c + s["radius"])
            rect = pygame.Rect(round(p0[0]), round(p1[1]), max(1, round(p1[0] - p0[0])), max(1, round(p0[1] - p1[1])))
            pygame.draw.ellipse(fg, _SHAPE["sphere"], rect)
            pygame.draw.ellipse(fg, COLORS["obstacle_edge"] + (255,), rect, 1)
            label_at = (rect.centerx - (font.size(s["name"])[0] // 2 if font else 0), rect.centery - 6)
        else:
            x, y = self._v2p(v, np.asarray(s["at"], np.float64)[[a, b]])
            col = _POINTS.get(s["name"].lower(), (40, 60, 160)) + (255,)
            pygame.draw.circle(fg, col, (x, y), 7, 2)
            pygame.draw.circle(fg, col, (x, y), 2)
            label_at = (round(x) + 8, round(y) - 16)
        if font is not None and label_at is not None and not s["name"].startswith("_"):
            white = s["kind"] == "sphere" or (s["kind"] == "box" and not self._aside(v, s))  # on the fill
            fg.blit(font.render(s["name"], True, (255, 255, 255) if white else COLORS["text"]), label_at)

    def _composite(self, band: np.ndarray | None, show_demos: bool, show_mean: bool,
                   scene: _Scene | None = None) -> pygame.Surface:
        digest = band_key(band)
        key = (digest, show_demos, show_mean, None if scene is None else scene.key)
        surf = self._composites.get(key)
        if surf is not None:
            return surf
        bg, fg = self._static_layers(show_demos, show_mean, scene)
        surf = bg.copy()
        if digest is not None:
            b = np.asarray(band, dtype=np.float64)
            for v in self.views:
                layer = band_layer(b[:, :, list(v.axes)], max(self.width, self.height), lambda q, v=v: self._v2p(v, q))
                surf.set_clip(v.rect)
                surf.blit(layer, (0, 0))
                surf.set_clip(None)
        surf.blit(fg, (0, 0))
        return self._composites.put(key, surf)

    # ------------------------------------------------------------------ frame
    def draw(self, surface: pygame.Surface, frame: TaskFrame, *, show_demos: bool = True, show_mean: bool = True,
             show_band: bool = True) -> None:
        """Draw one frame onto ``surface`` (at least W x H) at its top-left corner."""
        scene = self._scene(frame)
        surface.blit(self._composite(frame.band if show_band else None, show_demos, show_mean, scene), (0, 0))
        for k, v in enumerate(self.views):
            surface.set_clip(v.rect)
            self._draw_dynamic(surface, k, frame)
            surface.set_clip(None)
            if frame.human_active:
                pygame.draw.rect(surface, COLORS["human"], v.rect, 3)
        if self.strip_height > 0:
            self._draw_strip(surface, frame)

    def _scene(self, frame: TaskFrame) -> _Scene | None:
        """The frame's episode scene (adapted mean, via-points), checked against the task's sizes; None: none."""
        if frame.mean is None and frame.via is None:
            return None
        o = self.descriptor.out_dim
        mean = None if frame.mean is None else np.asarray(frame.mean, np.float64)
        if mean is not None and mean.shape != self.mean.shape:
            mean = None
        via = None if frame.via is None else np.asarray(frame.via, np.float64)
        if via is not None and (via.ndim != 2 or via.shape[1] != 1 + o or len(via) == 0):
            via = None
        if mean is None and via is None:
            return None
        return _Scene(mean, via, (band_key(mean), band_key(via)))

    def _draw_dynamic(self, surface: pygame.Surface, k: int, frame: TaskFrame) -> None:
        o = self.descriptor.out_dim
        if frame.trail is not None:
            trail = np.asarray(frame.trail, np.float64).reshape(-1, o)
            if len(trail) >= 2:
                pts = self.to_pixel(k, trail)
                pygame.draw.lines(surface, COLORS["trail"], False, pts, 1)
                pygame.draw.aalines(surface, COLORS["trail"], False, pts)
        if frame.correction is not None:
            ph = self.to_pixel(k, np.asarray(frame.correction, np.float64).reshape(o))
            mean = self.mean if frame.mean is None or np.shape(frame.mean) != self.mean.shape else \
                np.asarray(frame.mean, np.float64)
            n = int(round(float(np.clip(frame.phase, 0.0, 1.0)) * (len(mean) - 1)))
            origin = self.to_pixel(k, mean[n])
            pygame.draw.line(surface, COLORS["correction"], origin, ph, 2)
            pygame.draw.circle(surface, COLORS["correction"], origin, 3)
            for sx in (-1, 1):
                pygame.draw.line(surface, COLORS["correction"], ph + (-7, -7 * sx), ph + (7, 7 * sx), 3)
        robot = self.to_pixel(k, np.asarray(frame.position, np.float64).reshape(o))
        pygame.draw.circle(surface, COLORS["robot"], robot, self._r)
        pygame.draw.circle(surface, COLORS["robot_edge"], robot, self._r, 1)
        desired = self.to_pixel(k, np.asarray(frame.desired, np.float64).reshape(o))
        pygame.draw.circle(surface, COLORS["desired"], desired, self._r + 5, 2)

    def _draw_strip(self, surface: pygame.Surface, frame: TaskFrame) -> None:
        top = self.height - self.strip_height
        surface.fill(COLORS["strip"], pygame.Rect(0, top, self.width, self.strip_height))
        pygame.draw.line(surface, COLORS["strip_line"], (0, top), (self.width - 1, top))
        phase = float(np.clip(frame.phase, 0.0, 1.0)) if np.isfinite(frame.phase) else 0.0
        pygame.draw.rect(surface, COLORS["phase_bar"], pygame.Rect(0, top + 1, round(phase * self.width), 4))
        font = get_font(14)
        if font is None:
            return
        y, right = top + 9, self.width - 8
        if frame.human_active:
            badge = font.render(" HUMAN ", True, (255, 255, 255), COLORS["human"])
            right -= badge.get_width()
            surface.blit(badge, (right, y))
            right -= 8
        for line in frame.text:
            if y + font.get_linesize() > self.height:
                break
            img = self._text.get((14, str(line)))
            if img is None:
                if len(self._text) >= 256:
                    self._text.clear()
                img = self._text[(14, str(line))] = font.render(str(line), True, COLORS["text"], COLORS["strip"])
            surface.blit(img, (8, y), pygame.Rect(0, 0, max(0, right - 16), img.get_height()))
            y += font.get_linesize()

    def render_rgb(self, frame: TaskFrame, **flags: bool) -> np.ndarray:
        """(H, W, 3) uint8 RGB image of ``frame``, drawn offscreen (flags as :meth:`draw`)."""
        if self._offscreen is None:
            self._offscreen = pygame.Surface((self.width, self.height))
        self.draw(self._offscreen, frame, **flags)
        return surface_rgb(self._offscreen)
