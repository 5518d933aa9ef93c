"""The pieces :class:`~khgrl.common.tasks.render.TaskRenderer` is built from, apart from its layout: colours and
fonts, round tick values, the extent a task's views show, the exploration band's layer, the legend, a small cache of
composited surfaces and the RGB copy of a surface. Also used by what draws next to the task's views in the same style
(the human GUI's status strip and L(s) curves).
"""

from __future__ import annotations

import hashlib
import sys
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
import pygame
from khgrl.common.wire.descriptor import TaskDescriptor

__all__ = ["COLORS", "BAND_ALPHA", "get_font", "nice_ticks", "view_extent", "band_layer", "band_key",
           "SurfaceCache", "draw_legend", "draw_via", "surface_rgb"]

# Colours (RGB), matplotlib's tab palette where the paper's Fig. 3 (and common/kmp/plots.py) uses it.
COLORS: dict[str, tuple[int, int, int]] = {
    "background": (255, 255, 255),
    "grid": (232, 232, 236),
    "border": (150, 150, 160),
    "obstacle": (150, 82, 36),
    "obstacle_edge": (105, 52, 18),
    "demo": (150, 150, 158),
    "mean": (214, 39, 40),
    "band": (120, 185, 245),
    "desired": (255, 120, 0),
    "robot": (128, 36, 150),
    "robot_edge": (70, 10, 90),
    "trail": (150, 70, 175),
    "goal": (44, 160, 44),
    "start": (128, 36, 150),
    "correction": (0, 0, 0),
    "strip": (226, 226, 230),
    "strip_line": (190, 190, 198),
    "text": (25, 25, 30),
    "human": (255, 140, 0),
    "phase_bar": (120, 120, 135),
    "via": (0, 140, 140),
}
BAND_ALPHA = 95  # 0..255, translucency of the exploration band

_FONT_CACHE: dict[int, pygame.font.Font] = {}


def get_font(px: int) -> pygame.font.Font | None:
    """A monospace font if the system has one, else pygame's bundled default font (works headless).

    :param px: nominal font size in pixels.
    :return: the (cached) font, or None when pygame was built without font support.
    """
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


def nice_ticks(lo: float, hi: float, target: int = 5) -> np.ndarray:
    """Round tick values (steps 1, 2, 5 x 10^k) inside [lo, hi], about ``target`` of them."""
    span = hi - lo
    if not (np.isfinite(span) and span > 0):
        return np.array([lo])
    raw = span / max(1, target)
    mag = 10.0 ** np.floor(np.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 5.0, 10.0) if m * mag >= raw * 0.999)
    start = np.ceil(lo / step - 1e-9) * step
    return np.round(np.arange(start, hi + 1e-9 * span, step), 12)


def view_extent(d: TaskDescriptor) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) per output drawn: the workspace widened to shapes, demos and mean (by at most a quarter
    of the workspace on each side), plus 3 % padding."""
    wlo, whi = np.asarray(d.workspace_low, np.float64), np.asarray(d.workspace_high, np.float64)
    pts = [wlo[None], whi[None], np.asarray(d.mean, np.float64).reshape(-1, d.out_dim),
           np.asarray(d.demos, np.float64).reshape(-1, d.out_dim)]
    for s in d.shapes:
        if s["kind"] == "box":
            pts += [np.asarray(s["low"])[None], np.asarray(s["high"])[None]]
        elif s["kind"] == "sphere":
            c = np.asarray(s["center"], np.float64)
            pts += [(c - s["radius"])[None], (c + s["radius"])[None]]
        else:
            pts.append(np.asarray(s["at"], np.float64)[None])
    allp = np.concatenate(pts)
    allp = np.where(np.isfinite(allp), allp, wlo)
    span = whi - wlo
    lo = np.maximum(allp.min(axis=0), wlo - 0.25 * span)
    hi = np.minimum(allp.max(axis=0), whi + 0.25 * span)
    pad = 0.03 * (hi - lo)
    return lo - pad, hi + pad


def _fractions(steps: np.ndarray) -> np.ndarray:
    """concatenate(arange(m) / m for m in steps), vectorised."""
    starts = np.repeat(np.cumsum(steps) - steps, steps)
    return (np.arange(int(steps.sum())) - starts) / np.repeat(steps, steps)


def band_layer(band: np.ndarray, size: int, w2p: Callable[[np.ndarray], np.ndarray]) -> pygame.Surface:
    """The region swept by the per-point boxes [low, high] along the grid, as one uniform translucent
    layer (colour-keyed surface + surface alpha, so overlaps do not darken).

    The sweep between two consecutive boxes is their convex hull, which for axis-aligned boxes is the
    union of the linearly interpolated boxes; the boxes are therefore resampled to move at most about
    one pixel per sample and their union is rasterised (exact to a pixel).

    :param band: (N, 2, 2) per grid point [low, high] of the two axes drawn; rows with non-finite values are skipped.
    :param size: side of the (square) layer in pixels.
    :param w2p: (..., 2) axis values -> float pixel coordinates (x right, y down).
    :raises ValueError: if ``band`` is not (N, 2, 2).
    """
    band = np.asarray(band, dtype=np.float64)
    if band.ndim != 3 or band.shape[1:] != (2, 2):
        raise ValueError(f"band must be (N, 2, 2) [low, high] per point, got {band.shape}")
    band = band[np.all(np.isfinite(band), axis=(1, 2))]
    lo = np.minimum(band[:, 0], band[:, 1])
    hi = np.maximum(band[:, 0], band[:, 1])
    # pixel box per point: (left, top, right, bottom); y flips, so the high value is the pixel top
    boxes = np.c_[w2p(np.c_[lo[:, 0], hi[:, 1]]), w2p(np.c_[hi[:, 0], lo[:, 1]])]  # (N, 4)
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
    cover = np.cumsum(np.cumsum(diff.reshape(stride, stride), axis=0, dtype=np.int32), axis=1, dtype=np.int32)
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

    def get(self, key: tuple) -> Any:
        surf = self._items.get(key)
        if surf is not None:
            self._items.move_to_end(key)
        return surf

    def put(self, key: tuple, surf: Any) -> Any:
        self._items[key] = surf
        while len(self._items) > self.size:
            self._items.popitem(last=False)
        return surf


def draw_via(surface: pygame.Surface, at, r: int) -> None:
    """A via-point's marker: a teal diamond of half-width ``r`` pixels with a dot, centred on ``at`` (x, y)."""
    x, y = float(at[0]), float(at[1])
    col = COLORS["via"] + (255,)
    pygame.draw.polygon(surface, col, [(x - r, y), (x, y - r), (x + r, y), (x, y + r)], 2)
    pygame.draw.circle(surface, col, (x, y), 2)


def _legend_symbol(surface: pygame.Surface, kind: str, x0: int, cy: int, w: int) -> None:
    """One legend entry's symbol, ``w`` pixels wide from x0, centred on row cy (as the renderer draws it)."""
    cx = x0 + w // 2
    if kind == "demo":
        pygame.draw.line(surface, COLORS["demo"] + (255,), (x0, cy), (x0 + w, cy), 1)
    elif kind == "mean":
        pygame.draw.line(surface, COLORS["mean"] + (255,), (x0, cy), (x0 + w, cy), 2)
    elif kind == "band":
        col = tuple(round(255 + (c - 255) * BAND_ALPHA / 255) for c in COLORS["band"])
        pygame.draw.rect(surface, col + (255,), pygame.Rect(x0, cy - 5, w, 10))
    elif kind == "via":
        draw_via(surface, (cx, cy), 6)
    elif kind == "robot":
        pygame.draw.circle(surface, COLORS["robot"] + (255,), (cx, cy), 5)
    elif kind == "desired":
        pygame.draw.circle(surface, COLORS["desired"] + (255,), (cx, cy), 6, 2)
    elif kind == "correction":
        for sx in (-1, 1):
            pygame.draw.line(surface, COLORS["correction"] + (255,), (cx - 5, cy - 5 * sx), (cx + 5, cy + 5 * sx), 2)


def draw_legend(surface: pygame.Surface, at: tuple[int, int], entries: list[tuple[str, str]]) -> None:
    """A key in a white box with its top-left corner at ``at``: one row per (symbol kind, label).

    :param surface: where to draw (straight alpha or opaque).
    :param at: (x, y) pixel of the box's top-left corner.
    :param entries: (kind, label) with kind one of demo, mean, via, band, robot, desired, correction.
    """
    font = get_font(12)
    if font is None or not entries:
        return
    row, pad, sym = 16, 6, 22
    text_w = max(font.size(label)[0] for _, label in entries)
    box = pygame.Rect(at[0], at[1], pad * 3 + sym + text_w, pad * 2 + row * len(entries))
    pygame.draw.rect(surface, (255, 255, 255, 225), box, border_radius=4)
    pygame.draw.rect(surface, COLORS["border"] + (255,), box, 1, border_radius=4)
    for i, (kind, label) in enumerate(entries):
        cy = box.top + pad + row * i + row // 2
        _legend_symbol(surface, kind, box.left + pad, cy, sym)
        img = font.render(label, True, COLORS["text"])
        surface.blit(img, (box.left + pad * 2 + sym, cy - img.get_height() // 2))


def surface_rgb(surf: pygame.Surface) -> np.ndarray:
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
