"""pygame scene renderer for the passage world (paper Fig. 3 look).

``SceneRenderer`` draws on an offscreen ``pygame.Surface`` and never touches ``pygame.display``, so
``render_rgb`` works headless (no window, no SDL video driver needed). ``HumanWindow`` is the
``render_mode="human"`` counterpart: it owns the one pygame display window.

Layout: the unit square [0, 1]^2 (y up) fills a ``size`` x ``size`` square at the top of the frame;
a light grey text strip of ``strip_height`` pixels sits below it.

Speed: everything that does not change within an episode (grid, walls, gaps, obstacle, demonstrations,
KMP mean, goal, start) is drawn once, 2x supersampled and smooth-scaled down (cheap antialiasing), into a
cached layer; the exploration band, which changes only when the scale L changes, is composited into that
layer and cached by the band's content. A frame is then one blit plus a few small dynamic shapes.
"""

from __future__ import annotations

import hashlib
import sys
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import pygame

from common.scenarios import Scenario

__all__ = ["FrameState", "SceneRenderer", "HumanWindow", "COLORS"]

# Colours (RGB). Matplotlib's tab palette where Fig. 3 / plots.py uses it.
COLORS: dict[str, tuple[int, int, int]] = {
    "background": (255, 255, 255),
    "grid": (232, 232, 236),
    "grid_major": (214, 214, 222),
    "border": (150, 150, 160),
    "wall": (0, 0, 0),
    "gap": (255, 214, 40),
    "obstacle": (150, 82, 36),
    "obstacle_edge": (105, 52, 18),
    "demo": (31, 119, 180),
    "mean": (214, 39, 40),
    "band": (120, 185, 245),
    "desired": (255, 120, 0),
    "robot": (128, 36, 150),
    "robot_edge": (70, 10, 90),
    "trail": (150, 70, 175),
    "goal": (44, 160, 44),
    "goal_edge": (30, 120, 30),
    "start": (128, 36, 150),
    "correction": (0, 0, 0),
    "strip": (226, 226, 230),
    "strip_line": (190, 190, 198),
    "text": (25, 25, 30),
    "human": (255, 140, 0),
    "phase_bar": (120, 120, 135),
}

_SUPERSAMPLE = 2  # static layer is drawn at this factor and smooth-scaled down
_BAND_ALPHA = 95  # 0..255, translucency of the exploration band
_CACHE_SIZE = 8  # composited (static + band) layers kept


@dataclass
class FrameState:
    """What changes from frame to frame."""

    robot: np.ndarray  # (2,) robot position
    desired: np.ndarray  # (2,) desired position P_t
    phase: float = 0.0  # s in [0, 1]
    trail: np.ndarray | None = None  # (k, 2) robot positions so far this episode
    band: np.ndarray | None = None  # (N, 2, 2): per grid point [low(x, y), high(x, y)]
    human_active: bool = False
    correction: np.ndarray | None = None  # (2,) the human's P_h while intervening
    text: list[str] = field(default_factory=list)  # status lines for the bottom strip


_FONT_CACHE: dict[int, pygame.font.Font] = {}


def _get_font(px: int) -> pygame.font.Font | None:
    """A monospace font if the system has one, else pygame's bundled default font (works headless)."""
    if px in _FONT_CACHE:
        return _FONT_CACHE[px]
    try:
        if not pygame.font.get_init():
            pygame.font.init()
    except Exception:  # pragma: no cover - pygame built without SDL_ttf
        return None
    font = None
    try:
        path = pygame.font.match_font("dejavusansmono,liberationmono,couriernew,ubuntumono,monospace")
        if path:
            font = pygame.font.Font(path, px)
    except Exception:
        font = None
    if font is None:
        font = pygame.font.Font(None, px + 4)  # bundled freesansbold; its nominal size runs small
    _FONT_CACHE[px] = font
    return font


def _dashed_runs(pts: np.ndarray, dash: float) -> list[np.ndarray]:
    """Split a polyline (k, 2) into the 'on' pieces of a dash pattern of period 2*dash (arc length)."""
    if len(pts) < 2:
        return []
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    total = arc[-1]
    runs = []
    start = 0.0
    while start < total:
        end = min(start + dash, total)
        inside = (arc > start) & (arc < end)
        p0 = pts[0] if start <= 0 else _interp_arc(pts, arc, start)
        p1 = _interp_arc(pts, arc, end)
        run = np.vstack([p0[None], pts[inside], p1[None]])
        if len(run) >= 2:
            runs.append(run)
        start += 2 * dash
    return runs


def _fractions(steps: np.ndarray) -> np.ndarray:
    """concatenate(arange(m) / m for m in steps), vectorised."""
    starts = np.repeat(np.cumsum(steps) - steps, steps)
    return (np.arange(int(steps.sum())) - starts) / np.repeat(steps, steps)


def _interp_arc(pts: np.ndarray, arc: np.ndarray, a: float) -> np.ndarray:
    return np.array([np.interp(a, arc, pts[:, 0]), np.interp(a, arc, pts[:, 1])])


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
        self._composites: OrderedDict[tuple, pygame.Surface] = OrderedDict()
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

    # ------------------------------------------------------------------ static layers
    def _static_layers(self, show_demos: bool, show_mean: bool) -> tuple[pygame.Surface, pygame.Surface]:
        """(background, foreground), drawn 2x supersampled and smooth-scaled down. The background (grid)
        is opaque; the foreground (obstacle, gaps, demos, mean, walls, start, goal, legend) has per-pixel
        alpha, is premultiplied and goes on top of the band."""
        key = (show_demos, show_mean)
        if key in self._static:
            return self._static[key]
        k = _SUPERSAMPLE
        big = self.size * k
        sc = self.scenario

        bg = pygame.Surface((big, big))
        bg.fill(COLORS["background"])
        for i in range(1, 20):
            v = i / 20.0
            col = COLORS["grid_major"] if i % 2 == 0 else COLORS["grid"]
            a = self._w2p(np.array([v, 0.0]), k)
            b = self._w2p(np.array([v, 1.0]), k)
            pygame.draw.line(bg, col, a, b, k)
            a = self._w2p(np.array([0.0, v]), k)
            b = self._w2p(np.array([1.0, v]), k)
            pygame.draw.line(bg, col, a, b, k)
        pygame.draw.rect(bg, COLORS["border"], pygame.Rect(0, 0, big, big), k)

        fg = pygame.Surface((big, big), pygame.SRCALPHA)
        fg.fill((0, 0, 0, 0))
        if sc.obstacle is not None:
            c = self._w2p(np.array(sc.obstacle.center), k)
            r = sc.obstacle.radius * self._span * k
            pygame.draw.circle(fg, COLORS["obstacle"], c, r)
            pygame.draw.circle(fg, COLORS["obstacle_edge"], c, r, 2 * k)

        wall_w = max(3, round(0.011 * self.size)) * k
        gap_w = max(wall_w + 4 * k, round(0.026 * self.size) * k)
        for wall in sc.walls:
            x0, y_hi = self._w2p(np.array([wall.x, wall.gap_hi]), k)
            _, y_lo = self._w2p(np.array([wall.x, wall.gap_lo]), k)
            gap = pygame.Rect(0, 0, gap_w, y_lo - y_hi)
            gap.center = (round(x0), round(0.5 * (y_lo + y_hi)))
            pygame.draw.rect(fg, COLORS["gap"], gap)

        if show_demos and self.demos is not None:
            dash = 0.012  # world units
            for d in self.demos:
                for run in _dashed_runs(d, dash):
                    pygame.draw.lines(fg, COLORS["demo"] + (220,), False, self._w2p(run, k), 2 * k)
        if show_mean and self.mean is not None and len(self.mean) >= 2:
            pts = self._w2p(self.mean, k)
            pygame.draw.lines(fg, COLORS["mean"] + (255,), False, pts, 3 * k)
            for p in (pts[0], pts[-1]):  # round caps
                pygame.draw.circle(fg, COLORS["mean"] + (255,), p, 1.5 * k)

        for wall in sc.walls:  # walls over the demonstrations (recorded before the walls were placed)
            x0, y_hi = self._w2p(np.array([wall.x, wall.gap_hi]), k)
            _, y_lo = self._w2p(np.array([wall.x, wall.gap_lo]), k)
            rect_top = pygame.Rect(round(x0 - wall_w / 2), 0, wall_w, round(y_hi))
            rect_bot = pygame.Rect(round(x0 - wall_w / 2), round(y_lo), wall_w, big - round(y_lo))
            pygame.draw.rect(fg, COLORS["wall"] + (255,), rect_top)
            pygame.draw.rect(fg, COLORS["wall"] + (255,), rect_bot)

        s = self._w2p(np.array(sc.start), k)
        pygame.draw.circle(fg, COLORS["start"] + (255,), s, 7 * k, 2 * k)
        g = self._w2p(np.array(sc.goal), k)
        gr = max(sc.goal_radius * self._span * k, 9 * k)
        pygame.draw.circle(fg, COLORS["goal"] + (40,), g, gr)
        pygame.draw.circle(fg, COLORS["goal_edge"] + (255,), g, gr, 2 * k)
        pygame.draw.circle(fg, COLORS["goal"] + (255,), g, 7 * k)

        if self.legend:
            self._draw_legend(fg, k, show_demos and self.demos is not None, show_mean and self.mean is not None)

        # fg is averaged down in premultiplied form (transparent = (0, 0, 0, 0) is then exact) and
        # blitted with BLEND_PREMULTIPLIED
        fg = fg.premul_alpha()
        layers = (pygame.transform.smoothscale(bg, (self.size, self.size)),
                  pygame.transform.smoothscale(fg, (self.size, self.size)))
        self._static[key] = layers
        return layers

    def _draw_legend(self, fg: pygame.Surface, k: int, demos: bool, mean: bool) -> None:
        """A small key in the top-left corner, drawn into the (supersampled) static foreground."""
        font = _get_font(12 * k)
        if font is None:
            return
        sc = self.scenario
        entries: list[tuple[str, str]] = []
        if demos:
            entries.append(("demo", "demonstrations"))
        if mean:
            entries.append(("mean", "KMP mean"))
        entries.append(("band", "exploration band"))
        entries.append(("gap", "passage"))
        if sc.obstacle is not None:
            entries.append(("obstacle", "obstacle"))
        entries += [("robot", "robot"), ("desired", "desired P_t"), ("goal", "goal")]
        row = 16 * k
        pad = 6 * k
        sym = 22 * k
        text_w = max(font.size(label)[0] for _, label in entries)
        box = pygame.Rect(6 * k, 6 * k, pad * 3 + sym + text_w, pad * 2 + row * len(entries))
        pygame.draw.rect(fg, (255, 255, 255, 225), box, border_radius=4 * k)
        pygame.draw.rect(fg, COLORS["border"] + (255,), box, k, border_radius=4 * k)
        for i, (kind, label) in enumerate(entries):
            cy = box.top + pad + row * i + row // 2
            x0 = box.left + pad
            cx = x0 + sym // 2
            if kind == "demo":
                for j in range(3):
                    a = x0 + j * 8 * k
                    pygame.draw.line(fg, COLORS["demo"] + (255,), (a, cy), (a + 5 * k, cy), 2 * k)
            elif kind == "mean":
                pygame.draw.line(fg, COLORS["mean"] + (255,), (x0, cy), (x0 + sym, cy), 3 * k)
            elif kind == "band":
                col = tuple(round(255 + (c - 255) * _BAND_ALPHA / 255) for c in COLORS["band"])
                pygame.draw.rect(fg, col + (255,), pygame.Rect(x0, cy - 5 * k, sym, 10 * k))
            elif kind == "gap":
                pygame.draw.rect(fg, COLORS["gap"] + (255,), pygame.Rect(cx - 5 * k, cy - 6 * k, 10 * k, 12 * k))
            elif kind == "obstacle":
                pygame.draw.circle(fg, COLORS["obstacle"] + (255,), (cx, cy), 6 * k)
            elif kind == "robot":
                pygame.draw.circle(fg, COLORS["robot"] + (255,), (cx, cy), 5 * k)
            elif kind == "desired":
                pygame.draw.circle(fg, COLORS["desired"] + (255,), (cx, cy), 6 * k, int(2.5 * k))
            elif kind == "goal":
                pygame.draw.circle(fg, COLORS["goal"] + (255,), (cx, cy), 5 * k)
            img = font.render(label, True, COLORS["text"])
            fg.blit(img, (x0 + sym + pad, cy - img.get_height() // 2))

    def _band_layer(self, band: np.ndarray) -> pygame.Surface:
        """The region swept by the per-point boxes [low, high] along the grid, as one uniform translucent
        layer (colour-keyed surface + surface alpha, so overlaps do not darken).

        The sweep between two consecutive boxes is their convex hull, which for axis-aligned boxes is the
        union of the linearly interpolated boxes; the boxes are therefore resampled to move at most about
        one pixel per sample and their union is rasterised (exact to a pixel)."""
        band = np.asarray(band, dtype=np.float64)
        if band.ndim != 3 or band.shape[1:] != (2, 2):
            raise ValueError(f"band must be (N, 2, 2) [low, high] per point, got {band.shape}")
        band = band[np.all(np.isfinite(band), axis=(1, 2))]
        lo = np.minimum(band[:, 0], band[:, 1])
        hi = np.maximum(band[:, 0], band[:, 1])
        # pixel box per point: (left, top, right, bottom); y flips, so world hi.y is the pixel top
        tl = self._w2p(np.c_[lo[:, 0], hi[:, 1]])
        br = self._w2p(np.c_[hi[:, 0], lo[:, 1]])
        boxes = np.c_[tl, br]  # (N, 4)
        if len(boxes) >= 2:
            move = np.abs(np.diff(boxes, axis=0)).max(axis=1)
            steps = np.clip(np.ceil(move), 1, 256).astype(np.int64)
            idx = np.repeat(np.arange(len(boxes) - 1), steps)
            frac = _fractions(steps)
            boxes = np.vstack([boxes[idx] + frac[:, None] * (boxes[idx + 1] - boxes[idx]), boxes[-1:]])
        # rasterise the union of the boxes with a 2-D difference array (no overdraw, ~1 ms)
        n = self.size
        left = np.clip(np.floor(boxes[:, 0]).astype(np.int64), 0, n)
        top = np.clip(np.floor(boxes[:, 1]).astype(np.int64), 0, n)
        right = np.clip(np.ceil(boxes[:, 2]).astype(np.int64) + 1, 0, n)
        bottom = np.clip(np.ceil(boxes[:, 3]).astype(np.int64) + 1, 0, n)
        keep = (right > left) & (bottom > top)
        left, top, right, bottom = left[keep], top[keep], right[keep], bottom[keep]
        stride = n + 1
        plus = np.concatenate([top * stride + left, bottom * stride + right])
        minus = np.concatenate([top * stride + right, bottom * stride + left])
        m = stride * stride
        diff = (np.bincount(plus, minlength=m) - np.bincount(minus, minlength=m)).astype(np.int32)
        diff = diff.reshape(stride, stride)
        cover = np.cumsum(np.cumsum(diff, axis=0, dtype=np.int32), axis=1, dtype=np.int32)
        mask = cover[:n, :n] > 0  # (rows = y, cols = x)
        key_col = (255, 0, 255)
        surf = pygame.Surface((n, n))
        surf.fill(key_col)
        surf.set_colorkey(key_col)
        pixels = pygame.surfarray.pixels2d(surf)  # (x, y) view
        pixels[mask.T] = surf.map_rgb(COLORS["band"])
        del pixels  # unlock
        surf.set_alpha(_BAND_ALPHA)
        return surf

    def _composite(self, band: np.ndarray | None, show_demos: bool, show_mean: bool) -> pygame.Surface:
        if band is None or len(band) == 0:
            digest = None
        else:
            b = np.ascontiguousarray(band, dtype=np.float64)
            digest = (b.shape, hashlib.blake2b(b.tobytes(), digest_size=16).digest())
        key = (digest, show_demos, show_mean)
        surf = self._composites.get(key)
        if surf is not None:
            self._composites.move_to_end(key)
            return surf
        bg, fg = self._static_layers(show_demos, show_mean)
        surf = bg.copy()
        if digest is not None:
            surf.blit(self._band_layer(band), (0, 0))
        surf.blit(fg, (0, 0), special_flags=pygame.BLEND_PREMULTIPLIED)
        self._composites[key] = surf
        while len(self._composites) > _CACHE_SIZE:
            self._composites.popitem(last=False)
        return surf

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
        font = _get_font(15)
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
