"""pygame scene renderer for the passage world (paper Fig. 3 look).

``SceneRenderer`` draws on an offscreen ``pygame.Surface`` and never touches ``pygame.display``, so
``render_rgb`` works headless (no window, no SDL video driver needed). ``HumanWindow`` is the
``render_mode="human"`` counterpart: it owns the one pygame display window.

Layout: the unit square [0, 1]^2 (y up) fills a ``size`` x ``size`` square at the top of the frame;
a light grey text strip of ``strip_height`` pixels sits below it.

Speed: everything that does not change within an episode (grid, walls, gaps, obstacle, demonstrations,
KMP mean, goal, start) is drawn once (``common/tasks/passage/render_layers.py``) into a cached layer; the exploration
band, which changes only when the scale L changes, is composited into that layer and cached by the band's
content. A frame is then one blit plus a few small dynamic shapes. Colours, fonts and ``FrameState`` live in
``common/tasks/passage/render_style.py`` and are re-exported here.
"""

from __future__ import annotations

import sys

import numpy as np
import pygame
from khgrl.common.tasks.passage.render_layers import SurfaceCache, band_key, band_layer, static_layers
from khgrl.common.tasks.passage.render_style import COLORS, FrameState, get_font
from khgrl.common.tasks.passage.scenarios import Scenario

__all__ = ["FrameState", "SceneRenderer", "HumanWindow", "COLORS", "get_font"]

_CACHE_SIZE = 8  # composited (static + band) layers kept


class SceneRenderer:
    """Draws a passage-world frame. No ``pygame.display`` calls: safe for headless rgb rendering."""

    def __init__(
        self,
        scenario: Scenario,
        demos: np.ndarray | None,
        mean: np.ndarray | None,
        size: int = 600,
        strip_height: int = 80,
        legend: bool = True,
    ) -> None:
        if size < 50:
            raise ValueError(f"size must be >= 50 pixels, got {size}")
        if strip_height < 0:
            raise ValueError(f"strip_height must be >= 0, got {strip_height}")
        self.scenario = scenario
        self.demos = None if demos is None else np.asarray(demos, dtype=np.float64)
        if self.demos is not None and (self.demos.ndim != 3 or self.demos.shape[2] != 2):
            raise ValueError(f"demos must be (M, N, 2), got {self.demos.shape}")
        self.mean = None if mean is None else np.asarray(mean, dtype=np.float64)
        if self.mean is not None and (self.mean.ndim != 2 or self.mean.shape[1] != 2):
            raise ValueError(f"mean must be (N, 2), got {self.mean.shape}")
        self.size = int(size)
        self.strip_height = int(strip_height)
        self.width = self.size
        self.height = self.size + self.strip_height
        self._span = float(self.size - 1)  # world [0, 1] -> pixel [0, size - 1]
        self._static: dict[tuple[bool, bool], tuple[pygame.Surface, pygame.Surface]] = {}
        self._composites = SurfaceCache(_CACHE_SIZE)
        self._offscreen: pygame.Surface | None = None
        self._text_cache: dict[str, pygame.Surface] = {}
        self._sprites: dict[str, pygame.Surface] = {}
        self._robot_radius = max(5, round(0.012 * self.size))
        self.legend = bool(legend) and self.size >= 300

    # ------------------------------------------------------------------ coordinates
    def _w2p(self, p: np.ndarray, k: float = 1.0) -> np.ndarray:
        """World -> float pixel coordinates at scale factor k (no rounding)."""
        p = np.asarray(p, dtype=np.float64)
        # keep far-off points (huge bands, diverged robots) within C int range for pygame
        p = np.clip(p, -2.0, 3.0)
        out = np.empty(p.shape, dtype=np.float64)
        out[..., 0] = p[..., 0] * self._span * k
        out[..., 1] = (1.0 - p[..., 1]) * self._span * k
        return out

    def world_to_pixel(self, p: np.ndarray) -> np.ndarray:
        """(..., 2) workspace coordinates -> integer pixel coordinates (x right, y down)."""
        p = np.asarray(p, dtype=np.float64)
        out = np.empty(p.shape, dtype=np.float64)
        out[..., 0] = p[..., 0] * self._span
        out[..., 1] = (1.0 - p[..., 1]) * self._span
        return np.rint(out).astype(np.int64)

    def pixel_to_world(self, px: np.ndarray) -> np.ndarray:
        """(..., 2) pixel coordinates -> workspace coordinates (float); inverse of ``world_to_pixel``."""
        px = np.asarray(px, dtype=np.float64)
        out = np.empty(px.shape, dtype=np.float64)
        out[..., 0] = px[..., 0] / self._span
        out[..., 1] = 1.0 - px[..., 1] / self._span
        return out

    # ------------------------------------------------------------------ cached layers
    def _static_layers(self, show_demos: bool, show_mean: bool) -> tuple[pygame.Surface, pygame.Surface]:
        """(background, foreground) of :func:`.render_layers.static_layers`, cached per flag pair."""
        key = (show_demos, show_mean)
        if key in self._static:
            return self._static[key]
        layers = static_layers(
            self.scenario,
            self.demos if show_demos else None,
            self.mean if show_mean else None,
            size=self.size,
            span=self._span,
            w2p=self._w2p,
            legend=self.legend,
        )
        self._static[key] = layers
        return layers

    def _composite(self, band: np.ndarray | None, show_demos: bool, show_mean: bool) -> pygame.Surface:
        digest = band_key(band)
        key = (digest, show_demos, show_mean)
        surf = self._composites.get(key)
        if surf is not None:
            return surf
        bg, fg = self._static_layers(show_demos, show_mean)
        surf = bg.copy()
        if digest is not None:
            surf.blit(band_layer(band, self.size, self._w2p), (0, 0))
        surf.blit(fg, (0, 0), special_flags=pygame.BLEND_PREMULTIPLIED)
        return self._composites.put(key, surf)

    # ------------------------------------------------------------------ frame
    def draw(
        self,
        surface: pygame.Surface,
        state: FrameState,
        *,
        show_demos: bool = True,
        show_mean: bool = True,
        show_band: bool = True,
    ) -> None:
        """Draw one frame onto ``surface`` (at least ``size`` x ``size + strip_height``)."""
        band = state.band if show_band else None
        surface.blit(self._composite(band, show_demos, show_mean), (0, 0))
        self._draw_dynamic(surface, state)
        if state.human_active:
            pygame.draw.rect(surface, COLORS["human"], pygame.Rect(0, 0, self.size, self.size), 4)
        if self.strip_height > 0:
            self._draw_strip(surface, state)

    def _draw_dynamic(self, surface: pygame.Surface, state: FrameState) -> None:
        if state.trail is not None:
            trail = np.asarray(state.trail, dtype=np.float64).reshape(-1, 2)
            if len(trail) >= 2:
                pts = self._w2p(trail)
                pygame.draw.aalines(surface, COLORS["trail"], False, pts)
                pygame.draw.lines(surface, COLORS["trail"], False, pts, 1)

        if state.correction is not None:
            ph = np.rint(self._w2p(np.asarray(state.correction, dtype=np.float64).reshape(2)))
            if self.mean is not None and len(self.mean) > 0:
                n = int(round(float(np.clip(state.phase, 0.0, 1.0)) * (len(self.mean) - 1)))
                origin = self._w2p(self.mean[n])
            else:
                origin = self._w2p(np.asarray(state.desired, dtype=np.float64).reshape(2))
            pygame.draw.line(surface, COLORS["correction"], origin, ph, 2)
            pygame.draw.aaline(surface, COLORS["correction"], origin, ph)
            self._blit_sprite(surface, "dot", origin)
            self._blit_sprite(surface, "cross", ph)

        self._blit_sprite(surface, "robot", self._w2p(np.asarray(state.robot, dtype=np.float64).reshape(2)))
        self._blit_sprite(surface, "ring", self._w2p(np.asarray(state.desired, dtype=np.float64).reshape(2)))

    def _blit_sprite(self, surface: pygame.Surface, kind: str, center: np.ndarray) -> None:
        sprite = self._sprites.get(kind)
        if sprite is None:
            sprite = self._sprites[kind] = self._make_sprite(kind)
        half = sprite.get_width() // 2
        cx, cy = (int(v) for v in np.rint(center))
        surface.blit(sprite, (cx - half, cy - half), special_flags=pygame.BLEND_PREMULTIPLIED)

    def _make_sprite(self, kind: str) -> pygame.Surface:
        """Small antialiased markers: drawn 4x supersampled, premultiplied, smooth-scaled down. The
        sprite has odd size so its centre pixel lands exactly on the marker's pixel."""
        k = 4
        r = self._robot_radius
        half = {"robot": r + 2, "ring": r + 8, "cross": 10, "dot": 5}[kind]
        dim = 2 * half + 1
        big = pygame.Surface((dim * k, dim * k), pygame.SRCALPHA)
        big.fill((0, 0, 0, 0))
        c = (dim * k / 2.0, dim * k / 2.0)
        if kind == "robot":
            pygame.draw.circle(big, COLORS["robot"] + (255,), c, r * k)
            pygame.draw.circle(big, COLORS["robot_edge"] + (255,), c, r * k, int(1.5 * k))
        elif kind == "ring":
            pygame.draw.circle(big, (255, 255, 255, 150), c, (r + 6.5) * k, int(4.5 * k))  # light halo
            pygame.draw.circle(big, COLORS["desired"] + (255,), c, (r + 5.5) * k, int(2.5 * k))
        elif kind == "cross":
            arm = 7 * k
            col = COLORS["correction"] + (255,)
            for sx in (-1, 1):
                pygame.draw.line(big, col, (c[0] - arm, c[1] - sx * arm), (c[0] + arm, c[1] + sx * arm), 3 * k)
        elif kind == "dot":
            pygame.draw.circle(big, COLORS["correction"] + (255,), c, 3 * k)
        else:  # pragma: no cover
            raise ValueError(kind)
        return pygame.transform.smoothscale(big.premul_alpha(), (dim, dim))

    def _draw_strip(self, surface: pygame.Surface, state: FrameState) -> None:
        top = self.size
        strip = pygame.Rect(0, top, self.width, self.strip_height)
        surface.fill(COLORS["strip"], strip)
        pygame.draw.line(surface, COLORS["strip_line"], (0, top), (self.width - 1, top), 1)
        # phase bar along the top of the strip
        phase = float(np.clip(state.phase, 0.0, 1.0))
        bar_h = 4
        pygame.draw.rect(surface, COLORS["phase_bar"], pygame.Rect(0, top + 1, round(phase * self.width), bar_h))
        font = get_font(15)
        if font is None:
            return
        y = top + bar_h + 5
        line_h = font.get_linesize()
        right = self.width - 8
        if state.human_active:
            badge = font.render(" HUMAN ", True, (255, 255, 255), COLORS["human"])
            right -= badge.get_width()
            surface.blit(badge, (right, y))
            right -= 8
        for line in state.text:
            if y + line_h > top + self.strip_height:
                break
            img = self._text_surface(font, str(line))
            clip = pygame.Rect(0, 0, max(0, right - 8), img.get_height())
            surface.blit(img, (8, y), clip)
            y += line_h

    def _text_surface(self, font: pygame.font.Font, line: str) -> pygame.Surface:
        """Rendered text lines are cached: status lines often repeat from frame to frame."""
        img = self._text_cache.get(line)
        if img is None:
            img = font.render(line, True, COLORS["text"], COLORS["strip"])
            if len(self._text_cache) >= 256:
                self._text_cache.clear()
            self._text_cache[line] = img
        return img

    def render_rgb(self, state: FrameState, **flags) -> np.ndarray:
        """(size + strip_height, size, 3) uint8 RGB frame, drawn offscreen."""
        if self._offscreen is None:
            self._offscreen = pygame.Surface((self.width, self.height))
        self.draw(self._offscreen, state, **flags)
        return _surface_rgb(self._offscreen)


def _surface_rgb(surf: pygame.Surface) -> np.ndarray:
    """(H, W, 3) uint8 copy of a surface. For 32-bit surfaces the channels are picked straight out of
    the pixel buffer (about 3x faster than ``pygame.image.tobytes``)."""
    w, h = surf.get_size()
    if surf.get_bytesize() != 4 or surf.get_locked():
        return np.frombuffer(pygame.image.tobytes(surf, "RGB"), dtype=np.uint8).reshape(h, w, 3).copy()
    out = np.empty((h, w, 3), dtype=np.uint8)
    buf = surf.get_buffer()
    try:
        raw = np.frombuffer(buf, dtype=np.uint8).reshape(h, surf.get_pitch())[:, : 4 * w].reshape(h, w, 4)
        for c, shift in enumerate(surf.get_shifts()[:3]):
            byte = shift // 8 if sys.byteorder == "little" else 3 - shift // 8
            out[..., c] = raw[..., byte]
        del raw
    finally:
        del buf  # releases the surface lock
    return out


class HumanWindow:
    """``render_mode="human"``: a pygame display window showing the renderer's frames.

    Works with ``SDL_VIDEODRIVER=dummy`` (no visible window). ``closed`` turns True when the user closes
    the window (or after ``close()``); ``show`` is then a no-op.
    """

    def __init__(self, renderer: SceneRenderer, title: str = "KhGRL passage world") -> None:
        self.renderer = renderer
        pygame.display.init()
        self.screen = pygame.display.set_mode((renderer.width, renderer.height))
        pygame.display.set_caption(title)
        self.clock = pygame.time.Clock()
        self.closed = False
        self.events: list[pygame.event.Event] = []  # the events of the last show(), for mouse input later

    def show(self, state: FrameState, fps: float | None = None) -> None:
        if self.closed:
            return
        self.events = pygame.event.get()
        if any(e.type == pygame.QUIT for e in self.events):
            self.close()
            return
        self.renderer.draw(self.screen, state)
        pygame.display.flip()
        if fps is not None and fps > 0:
            self.clock.tick(fps)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        pygame.display.quit()

    def __enter__(self) -> HumanWindow:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
