"""The look of a passage-world frame: colours, fonts and the per-frame state the renderer draws.

Shared by the scene renderer (``common/tasks/passage/render.py``, ``common/tasks/passage/render_layers.py``) and by
anything that draws
next to it in the same style (the human GUI's plots and status strip).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pygame

__all__ = ["COLORS", "BAND_ALPHA", "FrameState", "get_font"]

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

BAND_ALPHA = 95  # 0..255, translucency of the exploration band


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
