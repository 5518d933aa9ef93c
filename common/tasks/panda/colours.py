"""Which pixels of a rendered gym-hil frame show the cube, which the table, read from the model's colours.

The scene's lights are white, so shading scales a surface's RGB (ambient, diffuse) and adds grey (specular): its
hue is unchanged and its HSV saturation (max - min) / max falls only with the specular part. A surface's colour is
therefore its hue, from the model (its geom's rgba, its material's rgba, or the saturated pixels of its material's
texture), not tuned on frames. A pixel shows the surface if its hue is within ``hue_tol`` of the surface's and its
saturation is at least half the surface's; ``hue_tol`` is half the hue gap between the surface and the nearest other
saturated colour of the model (geoms, materials, textures), so that no other surface can pass. Colours darker than
``DARK`` (of full scale) carry no hue (an 8-bit (0, 0, 1) has "hue" 240) and count for no surface.

gym-hil's purple cube (rgba 0.6 0.3 0.6, hue 300 degrees) is 88 degrees from the nearest other colour (blue, the
floor's and sky's textures, 8-bit): tolerance 44. The floor's checker texture (hue 210) is 10.6 degrees from the
nearest colour that is not background (the arm's light blue, 199; the sky, also background, is left out): tolerance
5.3 (its rendered pixels: 208.7 to 211.4 degrees, 1st to 99th percentile, seed 0's frame).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

__all__ = ["Colour", "SceneColours", "SATURATED", "DARK", "hsv", "colour_of", "matches", "scene_colours",
           "gym_hil_colours"]

SATURATED = 0.2  # a colour with HSV saturation below this is grey: no hue
DARK = 0.1  # a colour darker than this (max channel, of full scale) is black: no hue


@dataclass(frozen=True)
class Colour:
    """What a surface's pixels look like: hue (degrees), minimum HSV saturation, hue tolerance (degrees)."""

    hue: float
    min_sat: float
    hue_tol: float


def hsv(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(hue in degrees [0, 360), HSV saturation [0, 1], value [0, 1]) of ``rgb`` (..., 3): uint8 (0..255) or
    float (0..1).

    :param rgb: colours.
    """
    rgb = np.asarray(rgb)
    rgb = rgb / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float64)
    mx, mn = rgb.max(-1), rgb.min(-1)
    span = mx - mn
    safe = np.where(span > 0, span, 1.0)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    hue = np.where(mx == r, (g - b) / safe % 6, np.where(mx == g, (b - r) / safe + 2, (r - g) / safe + 4))
    hue = np.where(span > 0, hue * 60.0, 0.0)
    sat = np.where(mx > 0, span / np.where(mx > 0, mx, 1.0), 0.0)
    return hue, sat, mx


def _gap(a: np.ndarray | float, b: float) -> np.ndarray:
    """Angular distance between hues (degrees)."""
    d = np.abs(np.asarray(a, np.float64) - b) % 360.0
    return np.minimum(d, 360.0 - d)


def _texture(model, tex: int) -> np.ndarray:
    """(pixels, 3) float 0..1: texture ``tex``'s RGB pixels."""
    adr, n = int(model.tex_adr[tex]), int(model.tex_nchannel[tex])
    size = int(model.tex_height[tex]) * int(model.tex_width[tex]) * n
    return np.asarray(model.tex_data[adr: adr + size], np.float64).reshape(-1, n)[:, :3] / 255.0


def _surface(model, gid: int) -> tuple[np.ndarray, int, int]:
    """(the RGB colours a geom shows (k, 3), its material, its texture) -- -1 where it has none."""
    mat = int(model.geom_matid[gid])
    if mat < 0:
        return model.geom_rgba[gid, None, :3].astype(np.float64), -1, -1
    tex = int(np.asarray(model.mat_texid[mat]).reshape(-1)[1 if np.size(model.mat_texid[mat]) > 1 else 0])
    if tex < 0:
        return model.mat_rgba[mat, None, :3].astype(np.float64), mat, -1
    return _texture(model, tex) * model.mat_rgba[mat, :3], mat, tex


def _hued(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(hue, saturation) of the colours among ``rgb`` (k, 3) that have a hue (saturated, not dark)."""
    h, s, v = hsv(rgb)
    keep = (s >= SATURATED) & (v >= DARK)
    return h[keep], s[keep]


def colour_of(model, geom: str, background: bool = False) -> Colour:
    """The named geom's colour (see the module docstring).

    :param model: the ``mujoco.MjModel``.
    :param geom: the geom's name.
    :param background: the geom is background (it hides nothing that matters): the sky, also background, may share
        its hue (gym-hil's floor and sky are both hue 210) and does not limit its tolerance.
    :raises ValueError: the geom has no single hue, or another colour of the model is within 10 degrees of it.
    """
    import mujoco

    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
    if gid < 0:
        raise KeyError(f"no geom {geom!r} in the model")
    own, mat, tex = _surface(model, gid)
    h, s = _hued(own)
    if not h.size:
        raise ValueError(f"geom {geom!r} is grey or black: no hue to find it by")
    hue = float(np.rad2deg(np.arctan2(np.sin(np.deg2rad(h)).mean(), np.cos(np.deg2rad(h)).mean())) % 360.0)
    if _gap(h, hue).max() > 5.0:
        raise ValueError(f"geom {geom!r} has more than one hue ({h.min():.0f} to {h.max():.0f} degrees)")
    shown = model.geom_rgba[:, 3] > 0
    others = [model.geom_rgba[np.flatnonzero(shown & (np.arange(model.ngeom) != gid)), :3],
              model.mat_rgba[np.arange(model.nmat) != mat, :3]]
    sky = int(mujoco.mjtTexture.mjTEXTURE_SKYBOX)
    others += [_texture(model, t) for t in range(model.ntex) if t != tex and not (background and
                                                                               model.tex_type[t] == sky)]
    oh, _ = _hued(np.concatenate(others).astype(np.float64))
    gap = float(_gap(oh, hue).min()) if oh.size else 180.0
    if gap < 10.0:
        raise ValueError(f"geom {geom!r} (hue {hue:.0f}) does not stand out: another colour is {gap:.0f} degrees "
                         "away")
    return Colour(hue=hue, min_sat=float(np.median(s)) / 2, hue_tol=gap / 2)


def matches(frame: np.ndarray, colour: Colour) -> np.ndarray:
    """(H, W) bool: the pixels of ``frame`` (H, W, 3; uint8 or float 0..1) that show ``colour``.

    :param frame: RGB image.
    :param colour: the surface's colour.
    """
    hue, sat, val = hsv(np.asarray(frame)[..., :3])
    return (sat >= colour.min_sat) & (val >= DARK) & (_gap(hue, colour.hue) <= colour.hue_tol)


@dataclass(frozen=True)
class SceneColours:
    """The colours :func:`~khgrl.common.tasks.panda.camera.locate_cube` tells apart: the cube's and the table's
    (what is neither may hide the cube)."""

    cube: Colour
    table: Colour


def scene_colours(model, cube: str = "block", table: str = "floor") -> SceneColours:
    """The cube's and the table's colours from the model (:func:`colour_of`).

    :param model: the ``mujoco.MjModel``.
    :param cube: the cube's geom.
    :param table: the geom the cube rests on.
    """
    return SceneColours(cube=colour_of(model, cube), table=colour_of(model, table, background=True))


@functools.cache
def gym_hil_colours() -> SceneColours:
    """The cube's and the table's colours in gym-hil's pick-cube scene (its ``assets/scene.xml``, loaded once)."""
    from importlib.resources import files

    import mujoco

    return scene_colours(mujoco.MjModel.from_xml_path(str(files("gym_hil") / "assets" / "scene.xml")))
