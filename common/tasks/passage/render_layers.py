"""The layers of a passage-world frame that do not change from step to step.

``static_layers`` draws what is fixed within an episode (grid, walls, gaps, obstacle, demonstrations, KMP
mean, goal, start, legend) 2x supersampled and smooth-scaled down (cheap antialiasing); ``band_layer``
rasterises the exploration band, which changes only when the scale L changes. ``SceneRenderer``
(``common/tasks/passage/render.py``) caches both and composites them; a frame is then one blit plus a few small shapes.

Coordinates: ``w2p(p, k)`` maps (..., 2) workspace points to float pixel coordinates at supersampling factor
``k`` (the renderer's ``_w2p``); ``span`` is the pixel length of the unit square's side (``size - 1``).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable

import numpy as np
import pygame
from khgrl.common.tasks.passage.render_style import BAND_ALPHA, COLORS, get_font
from khgrl.common.tasks.passage.scenarios import Scenario

__all__ = ["SUPERSAMPLE", "static_layers", "band_layer", "dashed_runs", "band_key", "SurfaceCache"]

SUPERSAMPLE = 2  # static layer is drawn at this factor and smooth-scaled down

WorldToPixel = Callable[..., np.ndarray]


def dashed_runs(pts: np.ndarray, dash: float) -> list[np.ndarray]:
    """Split a polyline (k, 2) into the 'on' pieces of a dash pattern of period 2*dash (arc length).

    :param pts: (k, 2) polyline.
    :param dash: length of one dash (and of one gap) in the polyline's units.
    :return: the dashes, each an (m, 2) polyline with m >= 2.
    """
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


def static_layers(
    scenario: Scenario,
    demos: np.ndarray | None,
    mean: np.ndarray | None,
    *,
    size: int,
    span: float,
    w2p: WorldToPixel,
    legend: bool,
) -> tuple[pygame.Surface, pygame.Surface]:
    """(background, foreground) at ``size`` x ``size`` pixels, drawn 2x supersampled and smooth-scaled down.

    The background (grid) is opaque; the foreground (obstacle, gaps, demos, mean, walls, start, goal,
    legend) has per-pixel alpha, is premultiplied and goes on top of the band (blit it with
    ``BLEND_PREMULTIPLIED``).

    :param scenario: the passage world.
    :param demos: (M, N, 2) demonstrations to draw dashed, or None.
    :param mean: (N, 2) KMP mean to draw, or None.
    :param size: side of the square in pixels.
    :param span: pixel length of the unit square's side (``size - 1``).
    :param w2p: world -> float pixel coordinates, ``w2p(p, k)`` at supersampling factor k.
    :param legend: draw the key in the top-left corner.
    """
    k = SUPERSAMPLE
    big = size * k
    bg = pygame.Surface((big, big))
    bg.fill(COLORS["background"])
    for i in range(1, 20):
        v = i / 20.0
        col = COLORS["grid_major"] if i % 2 == 0 else COLORS["grid"]
        a = w2p(np.array([v, 0.0]), k)
        b = w2p(np.array([v, 1.0]), k)
        pygame.draw.line(bg, col, a, b, k)
        a = w2p(np.array([0.0, v]), k)
        b = w2p(np.array([1.0, v]), k)
        pygame.draw.line(bg, col, a, b, k)
    pygame.draw.rect(bg, COLORS["border"], pygame.Rect(0, 0, big, big), k)

    fg = _foreground(scenario, demos, mean, size=size, span=span, w2p=w2p)
    if legend:
        _draw_legend(fg, k, scenario, demos is not None, mean is not None)
    # fg is averaged down in premultiplied form (transparent = (0, 0, 0, 0) is then exact) and
    # blitted with BLEND_PREMULTIPLIED
    fg = fg.premul_alpha()
    return (pygame.transform.smoothscale(bg, (size, size)),
            pygame.transform.smoothscale(fg, (size, size)))


def _foreground(
    sc: Scenario,
    demos: np.ndarray | None,
    mean: np.ndarray | None,
    *,
    size: int,
    span: float,
    w2p: WorldToPixel,
) -> pygame.Surface:
    """The supersampled foreground without the legend (straight alpha)."""
    k = SUPERSAMPLE
    big = size * k
    fg = pygame.Surface((big, big), pygame.SRCALPHA)
    fg.fill((0, 0, 0, 0))
    if sc.obstacle is not None:
        c = w2p(np.array(sc.obstacle.center), k)
        r = sc.obstacle.radius * span * k
        pygame.draw.circle(fg, COLORS["obstacle"], c, r)
        pygame.draw.circle(fg, COLORS["obstacle_edge"], c, r, 2 * k)

    wall_w = max(3, round(0.011 * size)) * k
    gap_w = max(wall_w + 4 * k, round(0.026 * size) * k)
    for wall in sc.walls:
        x0, y_hi = w2p(np.array([wall.x, wall.gap_hi]), k)
        _, y_lo = w2p(np.array([wall.x, wall.gap_lo]), k)
        gap = pygame.Rect(0, 0, gap_w, y_lo - y_hi)
        gap.center = (round(x0), round(0.5 * (y_lo + y_hi)))
        pygame.draw.rect(fg, COLORS["gap"], gap)

    if demos is not None:
        dash = 0.012  # world units
        for d in demos:
            for run in dashed_runs(d, dash):
                pygame.draw.lines(fg, COLORS["demo"] + (220,), False, w2p(run, k), 2 * k)
    if mean is not None and len(mean) >= 2:
        pts = w2p(mean, k)
        pygame.draw.lines(fg, COLORS["mean"] + (255,), False, pts, 3 * k)
        for p in (pts[0], pts[-1]):  # round caps
            pygame.draw.circle(fg, COLORS["mean"] + (255,), p, 1.5 * k)

    for wall in sc.walls:  # walls over the demonstrations (recorded before the walls were placed)
        x0, y_hi = w2p(np.array([wall.x, wall.gap_hi]), k)
        _, y_lo = w2p(np.array([wall.x, wall.gap_lo]), k)
        rect_top = pygame.Rect(round(x0 - wall_w / 2), 0, wall_w, round(y_hi))
        rect_bot = pygame.Rect(round(x0 - wall_w / 2), round(y_lo), wall_w, big - round(y_lo))
        pygame.draw.rect(fg, COLORS["wall"] + (255,), rect_top)
        pygame.draw.rect(fg, COLORS["wall"] + (255,), rect_bot)

    s = w2p(np.array(sc.start), k)
    pygame.draw.circle(fg, COLORS["start"] + (255,), s, 7 * k, 2 * k)
    g = w2p(np.array(sc.goal), k)
    gr = max(sc.goal_radius * span * k, 9 * k)
    pygame.draw.circle(fg, COLORS["goal"] + (40,), g, gr)
    pygame.draw.circle(fg, COLORS["goal_edge"] + (255,), g, gr, 2 * k)
    pygame.draw.circle(fg, COLORS["goal"] + (255,), g, 7 * k)
    return fg


def _draw_legend(fg: pygame.Surface, k: int, sc: Scenario, demos: bool, mean: bool) -> None:
    """A small key in the top-left corner, drawn into the (supersampled) static foreground."""
    font = get_font(12 * k)
    if font is None:
        return
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
        _draw_legend_symbol(fg, kind, k, x0, cy, sym)
        img = font.render(label, True, COLORS["text"])
        fg.blit(img, (x0 + sym + pad, cy - img.get_height() // 2))


def _draw_legend_symbol(fg: pygame.Surface, kind: str, k: int, x0: int, cy: int, sym: int) -> None:
    """One legend entry's symbol, ``sym`` pixels wide starting at x0, centred on row cy."""
    cx = x0 + sym // 2
    if kind == "demo":
        for j in range(3):
            a = x0 + j * 8 * k
            pygame.draw.line(fg, COLORS["demo"] + (255,), (a, cy), (a + 5 * k, cy), 2 * k)
    elif kind == "mean":
        pygame.draw.line(fg, COLORS["mean"] + (255,), (x0, cy), (x0 + sym, cy), 3 * k)
    elif kind == "band":
        col = tuple(round(255 + (c - 255) * BAND_ALPHA / 255) for c in COLORS["band"])
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


def band_layer(band: np.ndarray, size: int, w2p: WorldToPixel) -> pygame.Surface:
    """The region swept by the per-point boxes [low, high] along the grid, as one uniform translucent
    layer (colour-keyed surface + surface alpha, so overlaps do not darken).

    The sweep between two consecutive boxes is their convex hull, which for axis-aligned boxes is the
    union of the linearly interpolated boxes; the boxes are therefore resampled to move at most about
    one pixel per sample and their union is rasterised (exact to a pixel).

    :param band: (N, 2, 2) per grid point [low(x, y), high(x, y)]; rows with non-finite values are skipped.
    :param size: side of the square in pixels.
    :param w2p: world -> float pixel coordinates (``w2p(p)``, no supersampling).
    :raises ValueError: if ``band`` is not (N, 2, 2).
    """
    band = np.asarray(band, dtype=np.float64)
    if band.ndim != 3 or band.shape[1:] != (2, 2):
        raise ValueError(f"band must be (N, 2, 2) [low, high] per point, got {band.shape}")
    band = band[np.all(np.isfinite(band), axis=(1, 2))]
    lo = np.minimum(band[:, 0], band[:, 1])
    hi = np.maximum(band[:, 0], band[:, 1])
    # pixel box per point: (left, top, right, bottom); y flips, so world hi.y is the pixel top
    tl = w2p(np.c_[lo[:, 0], hi[:, 1]])
    br = w2p(np.c_[hi[:, 0], lo[:, 1]])
    boxes = np.c_[tl, br]  # (N, 4)
    if len(boxes) >= 2:
        move = np.abs(np.diff(boxes, axis=0)).max(axis=1)
        steps = np.clip(np.ceil(move), 1, 256).astype(np.int64)
        idx = np.repeat(np.arange(len(boxes) - 1), steps)
        frac = _fractions(steps)
        boxes = np.vstack([boxes[idx] + frac[:, None] * (boxes[idx + 1] - boxes[idx]), boxes[-1:]])
    # rasterise the union of the boxes with a 2-D difference array (no overdraw, ~1 ms)
    n = size
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
    surf.set_alpha(BAND_ALPHA)
    return surf


def band_key(band: np.ndarray | None) -> tuple | None:
    """A cache key of an exploration band's values (None: no band to draw)."""
    if band is None or len(band) == 0:
        return None
    b = np.ascontiguousarray(band, dtype=np.float64)
    return b.shape, hashlib.blake2b(b.tobytes(), digest_size=16).digest()


class SurfaceCache:
    """The last ``size`` composited (static layers + band) surfaces, least recently used dropped first.

    :param size: surfaces kept.
    """

    def __init__(self, size: int = 8) -> None:
        self.size = int(size)
        self._items: OrderedDict[tuple, pygame.Surface] = OrderedDict()

    def get(self, key: tuple) -> pygame.Surface | None:
        surf = self._items.get(key)
        if surf is not None:
            self._items.move_to_end(key)
        return surf

    def put(self, key: tuple, surf: pygame.Surface) -> pygame.Surface:
        self._items[key] = surf
        while len(self._items) > self.size:
            self._items.popitem(last=False)
        return surf
