"""Every step of every finished episode, kept in the run directory: ``RUN_DIR/actor-ID/steps/episode-NNNNNN.npz``.

What the actor saw and did at each step, for the tools that look at a run after it: ``khgrl view`` (a Rerun
recording of a finished run) and ``khgrl export --lerobot`` (the run's transitions as a LeRobot dataset). The
actor gathers an episode's steps in memory (a few list appends per step, no I/O in the control loop) and writes
the file when the episode finishes, as ``episodes.csv`` gets its row; an episode cut short by a stop has neither.
The file is written under a temporary name and renamed, so a killed actor never leaves half a file.

Arrays of one file (N steps taken, O the KMP's output dimension, H the horizon; ``allow_pickle=False``):

==================  ============  =======================================================================
name                shape, dtype  meaning
==================  ============  =======================================================================
``t``               (N,) int32    the step
``phase``           (N,) float64  the KMP input s_t of the step
``robot``           (N, O) f8     the robot's position after the step
``desired``         (N, O) f8     P_t, the position commanded at the step (eq. 5, or the human's eq. 6)
``mean``            (N, O) f8     the KMP mean at the step
``scale``           (N, O) f8     L at the step (the band about the mean is +-\\|N_t\\| L)
``p_h``             (N, O) f8     the human's P_h applied at the step; NaN where none was
``intervened``      (N,) bool     a correction drove the step
``physical``        (N,) bool     ... and it was a hand on the arm (``--physical``)
``clipped``         (N,) bool     the human's action was clipped to [-1, 1]
``rate_limited``    (N,) bool     P_t was slowed to the rate limits
``obs``             (N, D) f4     the policy's observation before the step (a camera task's: its state)
``action``          (N, A) f4     the stored action (the human's a_h where intervened)
``reward``          (N,) f8       the step's reward
``terminated``      (N,) bool     the task ended at the step (success or failure)
``truncated``       (N,) bool     the episode was cut at the step (time limit)
``final_obs``       (D,) f4       the observation after the last step
``kmp_mean``        (H, O) f8     the episode's KMP mean over the grid (adapted to its scene where it varies)
``kmp_projector``   (H, O, O) f8  its null-space projector N (the band's shape)
``via``             (V, 1+O) f8   the episode's via-points, [phase, position...] per row (V = 0: none)
``episode``         () int64      the episode (whole run, 1-based)
``image/KEY``       (N, H, W, C)  a camera task's image KEY before the step (uint8): what the policy saw
==================  ============  =======================================================================

Files are not compressed, a camera task's neither: zlib saves ~3 % of camera-like frames (two 128 x 128 cameras,
100 steps: 9.3 against 9.6 MB) for 0.55 s of the actor's loop at each episode's end, where writing takes 0.04 s.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from khgrl.common.delivery.camera_rows import state_of
from khgrl.common.wire.descriptor import STATE

__all__ = ["StepRecord", "read_steps", "steps_dir", "actor_dirs", "images_of", "image_keys", "STEP_FIELDS", "IMAGE"]

STEP_FIELDS = ("t", "phase", "robot", "desired", "mean", "scale", "p_h", "intervened", "physical", "clipped",
               "rate_limited", "obs", "action", "reward", "terminated", "truncated")
_DTYPES = {"t": np.int32, "phase": np.float64, "robot": np.float64, "desired": np.float64, "mean": np.float64,
           "scale": np.float64, "p_h": np.float64, "intervened": bool, "physical": bool, "clipped": bool,
           "rate_limited": bool, "obs": np.float32, "action": np.float32, "reward": np.float64, "terminated": bool,
           "truncated": bool}
_NAME = re.compile(r"^episode-(\d{6,})\.npz$")
IMAGE = "image/"  # a camera image's field: IMAGE + its key in the observation


def images_of(rec: dict) -> dict[str, np.ndarray]:
    """A step file's (or a row's) camera images by their observation key: ``{KEY: rec["image/KEY"]}``.

    :param rec: a dict of :func:`read_steps` or a listener's row
    """
    return {k[len(IMAGE):]: v for k, v in rec.items() if k.startswith(IMAGE)}


def image_keys(actor_dir: Path) -> tuple[str, ...]:
    """The camera image keys an actor's step files hold (its first file's; no arrays read): () for a vector task
    or an actor without files.

    :param actor_dir: ``RUN_DIR/actor-ID``.
    """
    files = _files(actor_dir)
    if not files:
        return ()
    with np.load(files[0][1], allow_pickle=False) as z:
        return tuple(k[len(IMAGE):] for k in z.files if k.startswith(IMAGE))


def _files(actor_dir: Path) -> list[tuple[int, Path]]:
    d = steps_dir(actor_dir)
    return sorted((int(m.group(1)), p) for p in (d.iterdir() if d.is_dir() else []) if (m := _NAME.match(p.name)))


def steps_dir(actor_dir: Path) -> Path:
    """``RUN_DIR/actor-ID/steps``."""
    return Path(actor_dir) / "steps"


def actor_dirs(run_dir: Path) -> list[tuple[str, Path]]:
    """The run's actors, by id: ``[(ID, RUN_DIR/actor-ID), ...]`` sorted by folder name.

    :param run_dir: the run directory.
    """
    return [(p.name[len("actor-"):], p) for p in sorted(Path(run_dir).glob("actor-*")) if p.is_dir()]


@dataclass
class _Episode:
    episode: int
    rows: dict = field(default_factory=lambda: {k: [] for k in STEP_FIELDS})
    scene: dict = field(default_factory=dict)


class StepRecord:
    """Gathers an episode's steps and writes them when it finishes.

    Listeners (a live viewer) get the same: ``start(episode, scene)``, ``step(episode, row)`` and
    ``finish(episode, arrays, stats)`` with the dicts described in the module docstring (a row: one step's values).

    :param actor_dir: ``RUN_DIR/actor-ID``; None: write no files (listeners still hear every step).
    :param listeners: objects told about every episode and step.
    """

    def __init__(self, actor_dir: Path | None, listeners: tuple = ()) -> None:
        self.dir = None if actor_dir is None else steps_dir(actor_dir)
        self.listeners = list(listeners)
        self._ep: _Episode | None = None
        self.written = 0

    @property
    def active(self) -> bool:
        """Whether anything is recorded (files or listeners)."""
        return self.dir is not None or bool(self.listeners)

    def start(self, episode: int, env) -> None:
        """A new episode, after the reset: its KMP (adapted to the scene where it varies) and via-points.

        :param episode: the episode (whole run).
        :param env: the actor's :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv`.
        """
        if not self.active:
            return
        model, o = env.mapping.model, env.mapping.model.out_dim
        via = [[float(env.mapping.phases[n]), *np.asarray(p, np.float64).reshape(-1)]
               for n, p in getattr(env, "via_points", None) or []]
        self._ep = _Episode(episode, scene={
            "kmp_mean": np.asarray(model.grid_mean, np.float64),
            "kmp_projector": np.asarray(model.grid_projector, np.float64),
            "via": np.asarray(via, np.float64).reshape(-1, 1 + o)})
        for lis in self.listeners:
            lis.start(episode, self._ep.scene)

    def step(self, obs, info: dict, env, reward: float, terminated: bool, truncated: bool, p_h, physical: bool
             ) -> None:
        """One step just taken.

        :param obs: the observation the action was chosen on.
        :param info: the step's info (``KGRLEnv.step``).
        :param env: the environment after the step (its ``position``).
        :param reward: the step's reward.
        :param terminated: the task ended.
        :param truncated: the episode was cut.
        :param p_h: the human's P_h applied at the step, or None.
        :param physical: the correction was a hand on the arm.
        """
        if self._ep is None:
            return
        iv = bool(info["intervened"])
        row = {"t": int(info["t"]), "phase": float(info["phase"]), "robot": np.array(env.position, np.float64),
               "desired": info["desired"], "mean": env.mapping.mean(int(info["t"])), "scale": info["scale"],
               "p_h": p_h if iv and p_h is not None else np.full(len(env.position), np.nan), "intervened": iv,
               "physical": iv and bool(physical), "clipped": bool(info["clipped"]),
               "rate_limited": bool(info.get("rate_limited", False)), "obs": state_of(obs), "action": info["action"],
               "reward": float(reward), "terminated": bool(terminated), "truncated": bool(truncated)}
        if isinstance(obs, dict):
            row.update({IMAGE + k: v for k, v in obs.items() if k != STATE})  # (each step's own arrays, as a batch's)
        for k, v in row.items():
            self._ep.rows.setdefault(k, []).append(v)
        for lis in self.listeners:
            lis.step(self._ep.episode, row)

    def finish(self, final_obs, stats=None) -> Path | None:
        """The episode finished: write its file (temporary name, then renamed); returns its path.

        :param final_obs: the observation after the last step.
        :param stats: the episode's :class:`~khgrl.common.metrics.EpisodeStats` (for listeners).
        """
        ep, self._ep = self._ep, None
        if ep is None or not ep.rows["t"]:
            return None
        arrays = {k: np.asarray(v, dtype=_DTYPES.get(k, np.uint8)) for k, v in ep.rows.items()}
        arrays.update(ep.scene, final_obs=np.asarray(state_of(final_obs), np.float32), episode=np.int64(ep.episode))
        for lis in self.listeners:
            lis.finish(ep.episode, arrays, stats)
        if self.dir is None:
            return None
        self.dir.mkdir(parents=True, exist_ok=True)
        path = self.dir / f"episode-{ep.episode:06d}.npz"
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
        self.written += 1
        return path

    def close(self) -> None:
        """The actor stops: listeners with a ``close()`` (a live viewer sending its last data) are closed."""
        for lis in self.listeners:
            close = getattr(lis, "close", None)
            if callable(close):
                close()


def read_steps(actor_dir: Path) -> list[dict[str, np.ndarray]]:
    """The step files of an actor, in episode order, as dicts of arrays (``allow_pickle=False``); raises
    ValueError for a file that lacks a field or whose fields disagree in length.

    :param actor_dir: ``RUN_DIR/actor-ID``.
    """
    out = []
    for _, path in _files(actor_dir):
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        missing = [k for k in (*STEP_FIELDS, "final_obs", "kmp_mean", "kmp_projector", "via", "episode")
                   if k not in data]
        if missing:
            raise ValueError(f"{path}: missing {', '.join(missing)}")
        n = len(data["t"])
        if any(len(data[k]) != n for k in (*STEP_FIELDS, *(IMAGE + c for c in images_of(data)))):
            raise ValueError(f"{path}: the per-step arrays differ in length")
        out.append(data)
    return out
