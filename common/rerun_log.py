"""What a run looks like in Rerun (https://rerun.io, ``rerun-sdk`` 0.41): one module that logs a task's scene, an
episode's start, a step and an episode's end, used by the actor's live view (:mod:`khgrl.actor.viewer`, ``khgrl up
--view rerun``) and by ``khgrl view RUN_DIR`` (:mod:`khgrl.deploy.tools.view_cmd`), so both give the same entities.

Entities (positions in the task's command coordinates; a 2-D task at z = 0, an O > 3 task's first 3 outputs):

======================================  ===============================  =========================================
entity                                  what                             when
======================================  ===============================  =========================================
``/task/demos``                         LineStrips3D: the demonstrations static
``/task/workspace``                     Boxes3D: the workspace box       static
``/task/shapes/NAME``                   the task's shapes (Boxes3D,      static
                                        Ellipsoids3D, Points3D)
``/actor/ID/kmp/mean``                  LineStrips3D: the episode's KMP  each episode (step 0)
                                        mean (adapted to its scene)
``/actor/ID/via``                       Points3D: the episode's          each episode (step 0; cleared if none)
                                        via-points
``/actor/ID/robot``                     Points3D: the robot after step t each step
``/actor/ID/path``                      LineStrips3D: its path so far    every 10th step and the last
``/actor/ID/desired``                   Points3D: P_t                    each step
``/actor/ID/band/now``                  Boxes3D: mean_t +- abs(N_t) L_t  each step
``/actor/ID/p_h``                       Points3D: the human's P_h        each intervened step (cleared after)
``/actor/ID/intervened``                Scalars: 1 where a correction    each step
                                        drove the step, else 0
``/actor/ID/scale``                     Scalars: L_t, one per output     each step
``/actor/ID/camera``                    EncodedImage (JPEG): MuJoCo's    every K steps (``--view-camera-every``)
                                        camera
``/actor/ID/images/KEY``                EncodedImage (JPEG; Image if     every K steps (live), every step
                                        not RGB): a camera task's image  (``khgrl view``)
                                        KEY, what the policy saw
``/actor/ID/band``                      LineStrips3D: the band's low and episode end (last step)
                                        high edge over the episode
``/actor/ID/episode/return``, ``.../    Scalars                          episode end (no ``step``)
success``, ``.../weights_version``
``/learner/...``                        Scalars: ``utd``, ``ingested``,  each learner status (``ingested``
                                        ``version``, ``grad_steps_per_s``  timeline)
======================================  ===============================  =========================================

Timelines: ``episode`` (the episode, whole run), ``step`` (the step within it), ``run_step`` (the actor's steps
over the whole run: one timeline to scrub across episodes) and ``ingested`` (the learner's stored transitions);
Rerun adds ``log_time`` (wall clock) to everything. One recording per run: application id ``khgrl``, recording id
the run id, whichever processes log into it.

One module of ~330 lines on purpose: the one definition of the entities both the live view and ``khgrl view``
log, so that the two cannot drift apart; the sink and the command are :mod:`~khgrl.deploy.run.view_sink` and
:mod:`~khgrl.deploy.tools.view_cmd`.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["APPLICATION_ID", "INSTALL_HINT", "VIEW_ENV", "ViewTarget", "RunLogger", "import_rerun", "has_display",
           "to3", "band_half", "band_edges", "open_recording", "blueprint"]

APPLICATION_ID = "khgrl"
INSTALL_HINT = "pip install 'khgrl[view]'"
VIEW_ENV = "KHGRL_VIEW"  # set by khgrl up --view for its children: where to send (JSON of ViewTarget)
PATH_EVERY = 10  # the path so far is logged every this many steps (and at the episode's end): O(N) points each time
FLUSH_TICK_S = 0.5  # the SDK's batcher sends every this long: larger chunks, a live view this much behind
_ROBOT, _DESIRED, _HUMAN, _MEAN, _BAND, _DEMO = ((40, 120, 220), (250, 160, 30), (220, 40, 40), (30, 30, 30),
                                                 (120, 180, 120), (150, 150, 150))


@dataclass(frozen=True)
class ViewTarget:
    """Where a process of a viewed run logs to, as ``khgrl up --view`` tells its children (``$KHGRL_VIEW``, JSON).

    :param url: the gRPC sink, ``rerun+http://127.0.0.1:PORT/proxy``.
    :param camera_every: the actor logs the simulator's camera image every this many steps (0: never).
    :param camera_size: its width and height in pixels.
    :param actors: the run's actor ids (the first sends the recording's layout, :func:`blueprint`).
    """

    url: str
    camera_every: int = 10
    camera_size: int = 256
    actors: tuple[str, ...] = ()

    def to_env(self) -> str:
        return json.dumps(asdict(self))

    @staticmethod
    def from_env(environ: dict | None = None) -> "ViewTarget | None":
        """The target in ``$KHGRL_VIEW``, or None (not viewed); ValueError for a malformed value."""
        raw = (os.environ if environ is None else environ).get(VIEW_ENV, "")
        if not raw:
            return None
        try:
            data = json.loads(raw)
            return ViewTarget(**{**data, "actors": tuple(data.get("actors", ()))})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"${VIEW_ENV} is not a view target ({exc}): {raw!r}") from exc


def has_display() -> bool:
    """Whether a native window can open here (``DISPLAY`` or ``WAYLAND_DISPLAY``): Rerun's native viewer needs one."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def import_rerun() -> Any:
    """The ``rerun`` module, imported only when something is viewed; ImportError naming the install if absent."""
    try:
        import rerun
    except ImportError as exc:
        raise ImportError(f"viewing a run needs the Rerun SDK (rerun-sdk 0.41): {INSTALL_HINT}") from exc
    return rerun


def to3(points: Any) -> np.ndarray:
    """Positions as 3-D points: (..., O) -> (..., 3); O < 3 padded with zeros (a 2-D task at z = 0), O > 3 the
    first three outputs.

    :param points: positions in command coordinates, last axis the output.
    """
    p = np.asarray(points, dtype=np.float64)
    o = p.shape[-1]
    if o >= 3:
        return p[..., :3]
    return np.concatenate([p, np.zeros((*p.shape[:-1], 3 - o))], axis=-1)


def band_half(projector: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Half-width of the exploration band, abs(N) L per output (as :meth:`KGRLMapping.band
    <khgrl.common.kmp.mapping.KGRLMapping.band>` draws it): (..., O, O) projectors and (..., O) scales -> (..., O).

    :param projector: the KMP's null-space projector(s) N.
    :param scale: the exploration scale(s) L.
    """
    return np.einsum("...ij,...j->...i", np.abs(np.asarray(projector, np.float64)), np.asarray(scale, np.float64))


def band_edges(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (N, O): the band mean_t +- abs(N_t) L_t at the N steps of one episode's step arrays
    (:mod:`khgrl.common.step_records`: ``t``, ``mean``, ``scale``, ``kmp_projector``).

    :param arrays: one episode's arrays.
    """
    proj = arrays["kmp_projector"]
    t = np.clip(np.asarray(arrays["t"], int), 0, len(proj) - 1)
    half = band_half(proj[t], arrays["scale"])
    return arrays["mean"] - half, arrays["mean"] + half


def open_recording(recording_id: str, *, url: str | None = None, save: str | None = None) -> Any:
    """A Rerun recording stream of the run (application ``khgrl``, recording id = the run id) sending to a gRPC
    server (``url``: the launcher's sink or a viewer) or into a file (``save``); neither: kept in memory.

    :param recording_id: the run id.
    :param url: ``rerun+http://HOST:PORT/proxy``.
    :param save: an .rrd path.
    """
    rr = import_rerun()
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id,
                             batcher_config=rr.ChunkBatcherConfig(flush_tick=FLUSH_TICK_S))
    if url:
        rec.connect_grpc(url)
    elif save:
        rec.save(save)
    return rec


def blueprint(actors: list[str], camera: bool = True, images: tuple[str, ...] = ()) -> Any:
    """The layout a recording opens with: the 3-D scene (task and actors) beside the first actor's camera and
    images, L over the run and the episodes' returns and successes; the time panel on ``run_step``.

    :param actors: the actor ids.
    :param camera: show the camera view (a task with a simulator camera).
    :param images: a camera task's image keys (one 2-D view each).
    """
    import rerun.blueprint as rrb

    scene = ["/task/**", *(f"/actor/{a}/**" for a in actors), *(f"- /actor/{a}/camera" for a in actors),
             *(f"- /actor/{a}/images/**" for a in actors)]
    side = [rrb.TimeSeriesView(name="L (exploration scale)", contents=[f"/actor/{a}/scale" for a in actors]),
            rrb.TimeSeriesView(name="episodes", contents=[f"/actor/{a}/episode/**" for a in actors]),
            rrb.TimeSeriesView(name="intervened", contents=[f"/actor/{a}/intervened" for a in actors])]
    if camera and actors:
        side.insert(0, rrb.Spatial2DView(name="camera", origin=f"/actor/{actors[0]}/camera"))
    if images and actors:
        side[:0] = [rrb.Spatial2DView(name=key, origin=f"/actor/{actors[0]}/images/{key}") for key in images]
    return rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(name="scene", origin="/", contents=scene),
                                        rrb.Vertical(*side), column_shares=[3, 2]),
                         rrb.TimePanel(timeline="run_step"), rrb.BlueprintPanel(state="collapsed"),
                         rrb.SelectionPanel(state="collapsed"))


class RunLogger:
    """Logs a run's scene, episodes and steps into a Rerun recording stream (the entities of the module docstring).

    :param rec: a ``rerun.RecordingStream``.
    :param actor: the actor id (entity ``/actor/ID``).
    """

    def __init__(self, rec: Any, actor: str) -> None:
        self.rr = import_rerun()
        self.rec = rec
        self.prefix = f"/actor/{actor}"
        self.path: list[np.ndarray] = []
        self.run_step = 0
        self._human = False  # P_h shown now (cleared at the next step without one)

    # ------------------------------------------------------------------ static
    def scene(self, demos: np.ndarray, workspace: tuple[Any, Any], shapes: tuple = ()) -> None:
        """The task's static scene: demonstrations (M, N, O), workspace box and shapes (``khgrl.task`` Cuboid,
        Sphere, Point).

        :param demos: the demonstrations.
        :param workspace: (low, high).
        :param shapes: the task view's shapes.
        """
        rr, log = self.rr, self.rec.log
        log("/task/demos", rr.LineStrips3D(list(to3(demos)), colors=[_DEMO], radii=[0.002]), static=True)
        lo, hi = to3(workspace[0]), to3(workspace[1])
        log("/task/workspace", rr.Boxes3D(mins=[lo], sizes=[hi - lo], colors=[(90, 90, 90)]), static=True)
        for s in shapes:
            self._shape(s)

    def _shape(self, s: Any) -> None:
        rr, path = self.rr, f"/task/shapes/{s.name}"
        if s.kind == "box":
            lo, hi = to3(s.low), to3(s.high)
            self.rec.log(path, rr.Boxes3D(mins=[lo], sizes=[hi - lo], labels=[s.name]), static=True)
        elif s.kind == "sphere":
            self.rec.log(path, rr.Ellipsoids3D(centers=[to3(s.center)], half_sizes=[[s.radius] * 3],
                                               labels=[s.name]), static=True)
        else:
            self.rec.log(path, rr.Points3D([to3(s.at)], labels=[s.name], radii=[0.01]), static=True)

    # ------------------------------------------------------------------ an episode
    def _time(self, episode: int, step: int | None, run_step: int | None = None) -> None:
        self.rec.set_time("episode", sequence=int(episode))
        self.rec.set_time("run_step", sequence=int(self.run_step if run_step is None else run_step))
        if step is None:
            self.rec.disable_timeline("step")
        else:
            self.rec.set_time("step", sequence=int(step))

    def start(self, episode: int, scene: dict[str, np.ndarray]) -> None:
        """An episode begins: its KMP mean (H, O) and via-points (V, 1 + O).

        :param episode: the episode (whole run).
        :param scene: ``kmp_mean``, ``kmp_projector``, ``via`` (:class:`~khgrl.common.step_records.StepRecord`).
        """
        rr = self.rr
        self.path = []
        self._time(episode, 0, self.run_step + 1)  # at the episode's first step (run_step is unique per step)
        self.rec.log(f"{self.prefix}/kmp/mean", rr.LineStrips3D([to3(scene["kmp_mean"])], colors=[_MEAN]))
        via = np.asarray(scene.get("via", np.zeros((0, 1))))
        if len(via):
            self.rec.log(f"{self.prefix}/via", rr.Points3D(to3(via[:, 1:]), radii=[0.012], colors=[(160, 60, 200)]))
        else:
            self.rec.log(f"{self.prefix}/via", rr.Clear(recursive=False))

    def step(self, episode: int, row: dict[str, Any], projector: np.ndarray) -> None:
        """One step (a :class:`~khgrl.common.step_records.StepRecord` row: ``t``, ``robot``, ``desired``, ``mean``,
        ``scale``, ``p_h``, ``intervened``).

        :param episode: the episode.
        :param row: the step's values.
        :param projector: (O, O) the KMP's projector N_t at the step.
        """
        rr, log, p = self.rr, self.rec.log, self.prefix
        self.run_step += 1
        self._time(episode, row["t"])
        robot = to3(row["robot"])
        self.path.append(robot)
        log(f"{p}/robot", rr.Points3D([robot], radii=[0.012], colors=[_ROBOT]))
        if int(row["t"]) % PATH_EVERY == 0:
            log(f"{p}/path", rr.LineStrips3D([np.asarray(self.path)], colors=[_ROBOT]))
        log(f"{p}/desired", rr.Points3D([to3(row["desired"])], radii=[0.008], colors=[_DESIRED]))
        half = band_half(projector, row["scale"])
        log(f"{p}/band/now", rr.Boxes3D(centers=[to3(row["mean"])], half_sizes=[to3(half)], colors=[_BAND]))
        iv = bool(row["intervened"])
        if iv and np.all(np.isfinite(row["p_h"])):
            log(f"{p}/p_h", rr.Points3D([to3(row["p_h"])], radii=[0.015], colors=[_HUMAN]))
            self._human = True
        elif self._human:
            log(f"{p}/p_h", rr.Clear(recursive=False))
            self._human = False
        log(f"{p}/intervened", rr.Scalars([float(iv)]))
        log(f"{p}/scale", rr.Scalars(np.asarray(row["scale"], np.float64)))

    def image(self, episode: int, t: int, rgb: np.ndarray, quality: int = 80, entity: str = "camera") -> None:
        """A camera image at step ``t`` (JPEG-compressed if RGB).

        :param episode: the episode.
        :param t: the step.
        :param rgb: (H, W, 3) uint8 (another channel count is logged uncompressed).
        :param quality: JPEG quality.
        :param entity: its entity under ``/actor/ID``: ``camera`` (the simulator's), ``images/KEY`` (a camera
            task's image KEY)
        """
        self._time(episode, t)
        image = self.rr.Image(rgb)
        self.rec.log(f"{self.prefix}/{entity}", image.compress(jpeg_quality=quality) if rgb.shape[-1:] == (3,)
                     else image)

    def finish(self, episode: int, arrays: dict[str, np.ndarray], ret: float, success: bool,
               weights_version: int | None = None) -> None:
        """An episode ended: its band over the steps taken, its return and success.

        :param episode: the episode.
        :param arrays: its step arrays (:mod:`khgrl.common.step_records`).
        :param ret: its return.
        :param success: whether it succeeded.
        :param weights_version: the policy weights it ended with (the live view; None: not logged).
        """
        rr, log, p = self.rr, self.rec.log, self.prefix
        if self._human:
            log(f"{p}/p_h", rr.Clear(recursive=False))
            self._human = False
        if len(arrays["t"]):
            self._time(episode, int(arrays["t"][-1]))
            log(f"{p}/path", rr.LineStrips3D([to3(arrays["robot"])], colors=[_ROBOT]))
            low, high = band_edges(arrays)
            log(f"{p}/band", rr.LineStrips3D([to3(low), to3(high)], colors=[_BAND]))
        self._time(episode, None)
        log(f"{p}/episode/return", rr.Scalars([float(ret)]))
        log(f"{p}/episode/success", rr.Scalars([float(bool(success))]))
        if weights_version is not None:
            log(f"{p}/episode/weights_version", rr.Scalars([float(weights_version)]))

    # ------------------------------------------------------------------ the learner
    def learner(self, ingested: int, values: dict[str, float]) -> None:
        """Learner scalars (``/learner/NAME``) at ``ingested`` stored transitions.

        :param ingested: the learner's stored transitions (the ``ingested`` timeline).
        :param values: name -> value (non-finite values are skipped).
        """
        self.rec.reset_time()
        self.rec.set_time("ingested", sequence=int(ingested))
        for name, v in values.items():
            if v is not None and np.isfinite(float(v)):
                self.rec.log(f"/learner/{name}", self.rr.Scalars([float(v)]))
