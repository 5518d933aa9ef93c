"""The cube's position from gym-hil's ``front`` camera: what ``panda:pick``'s scene would read on a real robot.

The task's via-points come from the cube's true position in the observation; a real robot has only a camera. This
module estimates the cube's centre (x, y, z in the world frame, metres) from one RGB frame of the ``front`` camera:

1. **Colour segmentation** (:mod:`~khgrl.common.tasks.panda.colours`): the cube's pixels and the table's, each by
   its hue read from the model (geom / material / texture colours), not tuned on frames.
2. **Back-projection** of the cube pixels' centroid through the pinhole camera (vertical field of view
   ``model.cam_fovy``, square pixels, the image's size; MuJoCo's camera looks along its frame's -z, y up; pixel
   centres at +0.5, row 0 at the top) posed by ``data.cam_xpos`` / ``data.cam_xmat``, onto the plane z = ``CUBE_Z``:
   the cube is 4 cm wide (geom half-size 0.02 m) and lies on the table (the floor plane, z = 0) at every reset of
   ``panda:pick`` (gym-hil's ``_block_z``; the task's via-points, too, grasp at z = 0.02), so its centre is 0.02 m
   above the table; only (x, y) is estimated.
3. **The silhouette's fixed point.** The centroid of the cube's pixels is not the image of its centre: the camera
   looks down (about 35 degrees) on the top face and the near face, and at gym-hil's home pose the gripper's
   fingers hide part of the cube in many scenes (the far, upper part of its image; the bare centroid's checks
   reject 45 of 200), which pulls the centroid by up to 2 pixels (2 cm). So the estimate c is the point at which a
   cube would show the centroid seen: the predicted image of a cube at c is its silhouette (the convex hull of its 8
   projected corners, axis-aligned as ``panda:pick`` resets it; ``SUB`` x ``SUB`` samples a pixel) less the pixels
   that show neither the cube nor the table (what may stand in front of it: the arm), and c <- c + bp(seen
   centroid) - bp(predicted centroid), where bp is the back-projection, ``ITERATIONS`` times; the mean of the last
   half is the estimate (the sampled silhouette moves in steps, so the iteration jitters: by a fraction of a
   millimetre for a cube in full view, by 2 mm and more where the arm hides two thirds of it).
   ``occlusion=False`` subtracts nothing (only the silhouette's own offset is corrected: 0.05 pixel).

Not found is explicit: :func:`locate_cube` raises :class:`CubeNotFound` (the caller falls back or stops) when fewer
than 4 pixels match, when the cube's pixels touch the image's border (cut off), when the fixed point does not settle
(its last half spread over more than ``SETTLED``), when less than ``min_visible`` of the whole cube's silhouette is
seen, or when the pixels seen differ from the predicted visible area by more than ``max_mismatch`` (no cube on the
table explains the frame); ``min_visible`` 0.3 and ``max_mismatch`` 0.25 were set before any measurement, not
swept. Measured (``python -m khgrl.benchmarks.camera_scene``, 200 scenes, 128 x 128;
docs/camera_scene.json): found in 187, error in (x, y) mean 2.3 mm, p95 4.7 mm, max 6.4 mm; without the occlusion
model found in 155, p95 6.6 mm, max 12 mm.

Rendering (:func:`front_renderer`): MuJoCo's own ``mujoco.Renderer`` with shadows and reflections off and no
multisampling (``offsamples`` 0): 165 to 175 ms per 128 x 128 frame (median of 200, two runs, software EGL on the
loaded 2-core machine) where gym-hil's defaults (shadow map 4096, 8 samples) cost 1.7 to 2.2 s; locating the cube
costs about 55 ms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from khgrl.common.tasks.panda.colours import SceneColours, gym_hil_colours, matches, scene_colours

__all__ = ["CUBE_Z", "Camera", "CubeNotFound", "camera_of", "back_project", "project", "silhouette", "locate_cube",
           "describe_from_camera", "front_renderer", "render_front"]

CUBE_Z = 0.02  # the cube's centre above the table (half its 4 cm side; see the module docstring)
CUBE_HALF = 0.02  # half the cube's side (gym-hil's geom size)
ITERATIONS, SETTLED = 12, 2e-3  # the fixed point's iterations; its last half must lie within SETTLED (m)
SUB = 8  # sub-samples per pixel and axis of the predicted silhouette (a smooth function of the estimate)


class CubeNotFound(RuntimeError):
    """The frame does not show enough of the cube, or shows it where no cube could give it."""


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: pose in the world frame and vertical field of view.

    :param pos: (3,) the camera's position (``data.cam_xpos``).
    :param rot: (3, 3) the camera's axes as columns in the world frame (``data.cam_xmat``); it looks along -z.
    :param fovy: vertical field of view in degrees (``model.cam_fovy``).
    """

    pos: np.ndarray
    rot: np.ndarray
    fovy: float

    def focal(self, height: int) -> float:
        """Focal length in pixels for an image ``height`` pixels high.

        :param height: image height in pixels.
        """
        return 0.5 * height / np.tan(np.deg2rad(self.fovy) / 2)


def camera_of(model, data, name: str = "front") -> Camera:
    """The named camera's pose now and its field of view.

    :param model: the ``mujoco.MjModel``.
    :param data: the ``mujoco.MjData`` (after ``mj_forward``: its ``cam_xpos``/``cam_xmat``).
    :param name: the camera's name.
    """
    import mujoco

    cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
    if cid < 0:
        raise KeyError(f"no camera {name!r} in the model")
    return Camera(pos=np.array(data.cam_xpos[cid], np.float64), rot=np.array(data.cam_xmat[cid], np.float64)
                  .reshape(3, 3), fovy=float(model.cam_fovy[cid]))


def back_project(uv: np.ndarray, camera: Camera, size: tuple[int, int], z: float = CUBE_Z) -> np.ndarray:
    """(3,) the world point on the plane ``z`` seen at pixel ``uv`` = (column, row), pixel centres at +0.5, row 0 at
    the top (``mujoco.Renderer``'s images).

    :param uv: (2,) pixel coordinates (sub-pixel).
    :param camera: the camera.
    :param size: (height, width) of the image.
    :param z: the plane's height (metres).
    """
    h, w = size
    f = camera.focal(h)
    ray = camera.rot @ np.array([(uv[0] - w / 2) / f, -(uv[1] - h / 2) / f, -1.0])
    if ray[2] >= 0 and camera.pos[2] > z or ray[2] <= 0 and camera.pos[2] < z:
        raise CubeNotFound(f"pixel {tuple(uv)} does not look at the plane z = {z}")
    t = (z - camera.pos[2]) / ray[2]
    return camera.pos + t * ray


def project(points: np.ndarray, camera: Camera, size: tuple[int, int]) -> np.ndarray:
    """(..., 2) pixel coordinates (column, row) of world ``points`` (..., 3); the inverse of :func:`back_project`.

    :param points: world points in front of the camera.
    :param camera: the camera.
    :param size: (height, width) of the image.
    """
    h, w = size
    f = camera.focal(h)
    local = (np.asarray(points, np.float64) - camera.pos) @ camera.rot  # camera-frame coordinates
    depth = -local[..., 2]
    return np.stack([w / 2 + f * local[..., 0] / depth, h / 2 - f * local[..., 1] / depth], -1)


def _hull(points: np.ndarray) -> np.ndarray:
    """The convex hull of 2-D ``points`` (k, 2), counter-clockwise (in (column, row) axes), no repeated vertex."""
    pts = sorted(map(tuple, points))

    def chain(seq):
        out: list = []
        for p in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(chain(pts) + chain(pts[::-1]))


def silhouette(centre: np.ndarray, camera: Camera, size: tuple[int, int]) -> np.ndarray:
    """(H, W) float in [0, 1]: the fraction of each pixel covered by the image of an axis-aligned cube at
    ``centre`` (the convex hull of its 8 projected corners, a convex body's silhouette; ``SUB`` x ``SUB`` samples a
    pixel).

    :param centre: (3,) the cube's centre.
    :param camera: the camera.
    :param size: (height, width) of the image.
    """
    corners = centre + CUBE_HALF * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    poly = _hull(project(corners, camera, size))
    cover = np.zeros(size)
    lo = np.clip(np.floor(poly.min(0)).astype(int), 0, [size[1], size[0]])
    hi = np.clip(np.ceil(poly.max(0)).astype(int), 0, [size[1], size[0]])
    if np.any(hi <= lo):
        return cover
    offs = (np.arange(SUB) + 0.5) / SUB
    u = (np.arange(lo[0], hi[0])[:, None] + offs).reshape(-1)
    v = (np.arange(lo[1], hi[1])[:, None] + offs).reshape(-1)
    uu, vv = np.meshgrid(u, v)
    edge = np.roll(poly, -1, 0) - poly
    inside = np.all(edge[:, 0, None, None] * (vv - poly[:, 1, None, None])
                    - edge[:, 1, None, None] * (uu - poly[:, 0, None, None]) >= 0, axis=0)
    h, w = hi[1] - lo[1], hi[0] - lo[0]
    cover[lo[1]: hi[1], lo[0]: hi[0]] = inside.reshape(h, SUB, w, SUB).mean((1, 3))
    return cover


def _centroid(weights: np.ndarray) -> np.ndarray:
    """(column, row) of the weighted pixel centres."""
    rows, cols = np.indices(weights.shape)
    total = weights.sum()
    return np.array([(weights * (cols + 0.5)).sum() / total, (weights * (rows + 0.5)).sum() / total])


def locate_cube(frame: np.ndarray, camera: Camera, colours: SceneColours, *, occlusion: bool = True,
                min_visible: float = 0.3, max_mismatch: float = 0.25, z: float = CUBE_Z) -> np.ndarray:
    """(3,) the cube's centre (world frame, metres) seen in ``frame`` (see the module docstring).

    :param frame: (H, W, 3) RGB image from ``camera``.
    :param camera: the camera's pose and field of view when the frame was taken.
    :param colours: the cube's and the table's colours (:func:`~khgrl.common.tasks.panda.colours.scene_colours`).
    :param occlusion: model what hides the cube (else: the centroid of the cube's pixels, corrected only for the
        silhouette's own offset from the centre's image).
    :param min_visible: the cube's pixels / the silhouette's area at the estimate below this: not found.
    :param max_mismatch: |the cube's pixels - the predicted visible area| / the predicted visible area above this:
        no cube at the estimate explains the frame, not found.
    :param z: the height of the cube's centre (metres).
    :raises CubeNotFound: see above, and when the cube's pixels touch the image's border (cut off).
    """
    cube = matches(frame, colours.cube)
    size = cube.shape
    count = int(cube.sum())
    if count < 4:
        raise CubeNotFound(f"{count} pixels of the cube's colour")
    if cube[0].any() or cube[-1].any() or cube[:, 0].any() or cube[:, -1].any():
        raise CubeNotFound("the cube touches the image's border (cut off)")
    free = cube | matches(frame, colours.table) if occlusion else np.ones(size, bool)  # where the cube could be seen
    seen = _centroid(cube.astype(np.float64))
    target = back_project(seen, camera, size, z)
    est, trail = target, []
    for _ in range(ITERATIONS):  # est <- est + bp(seen) - bp(the centroid a cube at est would show)
        visible = silhouette(est, camera, size) * free
        if visible.sum() < 1.0:
            raise CubeNotFound("no cube on the table could show these pixels")
        est = est + target - back_project(_centroid(visible), camera, size, z)
        trail.append(est)
    last = np.array(trail[-ITERATIONS // 2:])  # the sampled silhouette moves in steps: the fixed point jitters
    if np.ptp(last[:, :2], 0).max() > SETTLED:
        raise CubeNotFound(f"the estimate did not settle (spread {np.ptp(last[:, :2], 0).max() * 1e3:.1f} mm)")
    est = last.mean(0)
    whole = silhouette(est, camera, size)
    visible, full = whole * free, whole.sum()
    if count < min_visible * full:
        raise CubeNotFound(f"{count} pixels of the cube's colour, {full:.0f} for the whole cube (too little seen)")
    if abs(count - visible.sum()) > max_mismatch * visible.sum():
        raise CubeNotFound(f"{count} pixels of the cube's colour where a cube would show {visible.sum():.0f}")
    return est


def describe_from_camera(frame: np.ndarray, camera: Camera, colours: SceneColours | None = None,
                         model=None) -> dict[str, float]:
    """The scene as :func:`~khgrl.common.tasks.panda.task.describe` gives it (``cube_x``, ``cube_y``, metres),
    from a front-camera frame.

    :param frame: (H, W, 3) RGB image.
    :param camera: the camera when the frame was taken (:func:`camera_of`).
    :param colours: the cube's and the table's colours (None: read from ``model``).
    :param model: the ``mujoco.MjModel`` to read the colours from (None with ``colours`` None: gym-hil's own
        pick-cube scene, ``gym_hil/assets/scene.xml``).
    :raises CubeNotFound: the cube is not found (:func:`locate_cube`).
    """
    if colours is None:
        colours = gym_hil_colours() if model is None else scene_colours(model)
    est = locate_cube(frame, camera, colours)
    return {"cube_x": float(est[0]), "cube_y": float(est[1])}


def front_renderer(model, size: int = 128):
    """A ``mujoco.Renderer`` for ``size`` x ``size`` frames with the cheap settings: shadows and reflections off,
    no multisampling (the model's ``offsamples`` is 0 while the renderer's context is made, then restored).

    :param model: the ``mujoco.MjModel`` (its offscreen buffer is enlarged to ``size`` if smaller).
    :param size: width and height in pixels.
    """
    import mujoco

    vis, quality = model.vis.global_, model.vis.quality
    vis.offwidth, vis.offheight = max(vis.offwidth, size), max(vis.offheight, size)
    samples = quality.offsamples
    quality.offsamples = 0
    try:
        renderer = mujoco.Renderer(model, height=size, width=size)
    finally:
        quality.offsamples = samples
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    return renderer


def render_front(renderer, model, data, name: str = "front") -> tuple[np.ndarray, Camera]:
    """(frame (H, W, 3) uint8, the camera it was taken with) of the named camera now.

    :param renderer: from :func:`front_renderer`.
    :param model: the ``mujoco.MjModel``.
    :param data: the ``mujoco.MjData`` (after ``mj_forward``).
    :param name: the camera's name.
    """
    renderer.update_scene(data, camera=name)
    return np.asarray(renderer.render(), np.uint8).copy(), camera_of(model, data, name)
