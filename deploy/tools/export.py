"""``khgrl export RUN_DIR --lerobot OUT``: a run's transitions as a LeRobot dataset (format v3.0, LeRobot's writer).

Source: every finished episode's steps, ``RUN_DIR/actor-ID/steps/episode-NNNNNN.npz``
(:mod:`khgrl.common.step_records`). One LeRobot episode per (actor, episode), in actor then episode order; one
frame per step. Features (:data:`FEATURES` says what each is):

* LeRobot's RL names: ``observation.state`` (the policy's observation before the step), ``action`` (the stored
  action: the human's a_h where a correction drove the step), ``next.reward``, ``next.done`` (True on an episode's
  last frame, whatever ended it: the task, a time limit or the N steps of the grid) and
  ``complementary_info.is_intervention`` (the per-transition flag of LeRobot's HIL-SERL: its actor puts
  ``is_intervention`` in each transition's complementary_info, its ReplayBuffer writes it under this name);
* KhGRL's extras: ``next.terminated``, ``observation.phase``, ``action.desired_position`` (P_t),
  ``next.observation.position`` (the robot after the step), ``complementary_info.kmp_mean`` (eta0_t),
  ``complementary_info.human_position`` (P_h; 0 where none) with ``complementary_info.human_position_valid``;
* a camera task's images, LeRobot's ``observation.images.KEY`` (dtype ``image``, (H, W, C) uint8 frames: what the
  policy saw before the step; ``observation.state`` is then its state vector).

Every frame's task is the run's task spec. Provenance (KhGRL's version, the run id, each dataset episode's actor
and run episode) goes to ``OUT/meta/khgrl.json``: LeRobot's ``meta/info.json`` has no field for it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from khgrl.common.lerobot.library import ACTION, DONE, INTERVENTION, REWARD, STATE
from khgrl.common.step_records import images_of
from khgrl.deploy.run.rundir import still_running

__all__ = ["add_parser", "export_run", "FEATURES", "DEFAULT_FPS"]

DEFAULT_FPS = 10  # a run without --rate has no real-time rate; 10 Hz is gym-hil's Panda's, as KhGRL steps it
FEATURES = {  # name: (step-record field, dtype, meaning)
    STATE: ("obs", "float32", "the policy's observation before the step"),
    ACTION: ("action", "float32", "the stored action in [-1, 1] (the human's a_h where intervened)"),
    REWARD: ("reward", "float32", "the step's reward"),
    DONE: (None, "bool", "the episode's last frame"),
    INTERVENTION: ("intervened", "bool", "a human correction drove the step"),
    "next.terminated": ("terminated", "bool", "the task ended at the step (success or failure)"),
    "observation.phase": ("phase", "float32", "the KMP input s_t of the step"),
    "action.desired_position": ("desired", "float32", "P_t, the position commanded (eq. 5, or the human's eq. 6)"),
    "next.observation.position": ("robot", "float32", "the robot's position after the step"),
    "complementary_info.kmp_mean": ("mean", "float32", "the KMP mean eta0_t of the step"),
    "complementary_info.human_position": ("p_h", "float32", "the human's P_h applied at the step (0 where none)"),
    "complementary_info.human_position_valid": (None, "bool", "human_position holds a P_h"),
}


IMAGES = "observation.images."  # + a camera task's image key (LeRobot's name for a camera's frames)


class ExportError(RuntimeError):
    """A run directory that cannot be exported (the message says why)."""


def _columns(rec: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One episode's steps as LeRobot columns, (F, *shape) in each feature's dtype."""
    f = len(rec["t"])
    p_h = np.asarray(rec["p_h"], np.float64)
    valid = np.isfinite(p_h).all(axis=1)
    done = np.zeros(f, bool)
    done[-1] = True
    cols = {name: np.asarray(rec[field]) for name, (field, _, _) in FEATURES.items() if field is not None}
    cols.update({DONE: done, "complementary_info.human_position": np.where(valid[:, None], p_h, 0.0),
                 "complementary_info.human_position_valid": valid})
    out = {name: np.ascontiguousarray(c.reshape(f, -1), dtype=FEATURES[name][1]) for name, c in cols.items()}
    return {**out, **{IMAGES + key.replace("/", "_"): np.asarray(frames, np.uint8)
                      for key, frames in images_of(rec).items()}}


def _features(columns: dict[str, np.ndarray]) -> dict[str, dict]:
    return {name: {"dtype": "image", "shape": tuple(int(d) for d in c.shape[1:]), "names": ["height", "width",
                                                                                            "channels"]}
            if name.startswith(IMAGES) else {"dtype": FEATURES[name][1], "shape": (int(c.shape[1]),), "names": None}
            for name, c in columns.items()}


def _episodes(run_dir: Path) -> list[tuple[str, dict[str, np.ndarray]]]:
    from khgrl.common.step_records import actor_dirs, read_steps

    found = []
    for actor, actor_dir in actor_dirs(run_dir):
        try:
            found += [(actor, rec) for rec in read_steps(actor_dir)]
        except (ValueError, OSError) as exc:
            raise ExportError(f"{actor_dir}: unreadable step records: {exc}") from None
    if not found:
        raise ExportError(f"{run_dir}: no step records (RUN_DIR/actor-ID/steps/episode-N.npz): not a run directory, "
                          f"no episode finished, or a run from before the actor kept them")
    return found


def _fps(fps: int | None, rate: float) -> tuple[int, str]:
    if fps is not None:
        if fps <= 0:
            raise ExportError(f"--fps {fps}: must be > 0")
        return fps, "--fps"
    if rate > 0:
        if abs(rate - round(rate)) > 1e-9:
            raise ExportError(f"the run's rate {rate} Hz is not a whole number (LeRobot's fps is an integer): "
                              f"give --fps")
        return int(round(rate)), "the run's rate"
    return DEFAULT_FPS, "default (the run had no --rate)"


def export_run(run_dir: str | Path, out: str | Path, *, fps: int | None = None, overwrite: bool = False,
               progress: bool = True) -> dict[str, Any]:
    """Write ``run_dir``'s step records as the LeRobot dataset ``out``; returns the provenance written with it.

    :param run_dir: a run directory (``khgrl up``'s, or processes started by hand with one ``--run-dir``).
    :param out: the dataset folder to write.
    :param fps: the dataset's fps (None: the run's ``rate`` if > 0, else :data:`DEFAULT_FPS`).
    :param overwrite: replace an existing ``out``.
    :param progress: show a progress bar (on a terminal).
    :raises ExportError: nothing to export, or settings that do not fit.
    :raises FileExistsError: ``out`` exists and not ``overwrite``.
    """
    from khgrl.common.lerobot.writer import Episode, write_dataset
    from khgrl.deploy.tools.eval_inputs import EvalError, read_config

    from khgrl import __version__

    run_dir, out = Path(run_dir), Path(out)
    if out.exists() and not overwrite:  # before any work
        raise FileExistsError(f"{out} exists: give --overwrite to replace it, or another output folder")
    _check_replace(run_dir, out)
    if not run_dir.is_dir():
        raise ExportError(f"{run_dir}: no such run directory")
    if running := still_running(run_dir, "khgrl export"):
        raise ExportError(running)
    try:
        cfg, runtime, _ = read_config(run_dir)
    except EvalError as exc:
        raise ExportError(str(exc)) from None
    found = _episodes(run_dir)
    fps_used, fps_from = _fps(fps, float(cfg.rate))
    task = cfg.task_spec
    episodes = [Episode(task, _columns(rec)) for _, rec in found]
    provenance = {"khgrl_version": __version__, "run": runtime.get("run"), "run_dir": str(run_dir.resolve()),
                  "task": task, "fps": fps_used, "fps_from": fps_from,
                  "features": {**{name: meaning for name, (_, _, meaning) in FEATURES.items()},
                               **{name: "a camera's frame before the step" for name in episodes[0].columns
                                  if name.startswith(IMAGES)}},
                  "episodes": [{"index": i, "actor": actor, "episode": int(rec["episode"]), "frames": len(rec["t"])}
                               for i, (actor, rec) in enumerate(found)]}
    with _Bar(len(episodes), progress) as bar:
        write_dataset(out, fps=fps_used, features=_features(episodes[0].columns), episodes=episodes,
                      overwrite=overwrite, sidecar=provenance, on_episode=lambda ep: bar.advance())
    return provenance


def _check_replace(run_dir: Path, out: Path) -> None:
    """``--overwrite`` replaces only a LeRobot dataset that khgrl export wrote: never the source run (nor a folder
    that holds it), never a folder that holds anything else (:func:`~khgrl.common.lerobot.writer.not_a_dataset`).

    :raises FileExistsError: naming why ``out`` is not replaced.
    """
    from khgrl.common.lerobot.writer import not_a_dataset

    if not (out.exists() or out.is_symlink()):
        return
    src, dst = run_dir.resolve(), out.resolve()
    if dst == src or dst in src.parents:
        raise FileExistsError(f"{out} is (or holds) the run being exported: not replaced; give another output folder")
    if why := not_a_dataset(out):
        raise FileExistsError(f"{out} is not a LeRobot dataset that khgrl export wrote ({why}): not replaced; "
                              f"give another output folder")


class _Bar:
    """A rich progress bar over the episodes on a terminal; nothing otherwise."""

    def __init__(self, total: int, enabled: bool) -> None:
        self._p = None
        if enabled and sys.stdout.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._p = Progress(TextColumn("episodes"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
            self._task = self._p.add_task("export", total=total)

    def __enter__(self) -> "_Bar":
        if self._p is not None:
            self._p.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._p is not None:
            self._p.stop()

    def advance(self) -> None:
        if self._p is not None:
            self._p.advance(self._task)


def _cmd_export(args: argparse.Namespace) -> int:
    from khgrl.common.lerobot.library import LeRobotMissing

    try:
        prov = export_run(args.run_dir, args.lerobot, fps=args.fps, overwrite=args.overwrite,
                          progress=not args.no_progress)
    except (ExportError, FileExistsError, LeRobotMissing) as exc:
        print(f"khgrl export: error: {exc}", file=sys.stderr)
        return 2
    frames = sum(e["frames"] for e in prov["episodes"])
    print(f"wrote {len(prov['episodes'])} episodes, {frames} frames at {prov['fps']} fps ({prov['fps_from']}) as "
          f"the LeRobot dataset {args.lerobot} (intervention flag: {INTERVENTION})")
    return 0


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``khgrl export`` on the subcommands ``sub`` of the ``khgrl`` parser.

    :param sub: the ``add_subparsers()`` object.
    """
    p = sub.add_parser("export", help="a run's transitions as a LeRobot dataset (pip install 'khgrl[lerobot]')",
                       description=__doc__.split("\n\n")[0].replace("``", ""))
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory (its actor-ID/steps/ records)")
    p.add_argument("--lerobot", metavar="OUT", required=True,
                   help="write a LeRobot dataset (v3.0) in folder OUT: one episode per (actor, episode), "
                        f"observation.state, action, next.reward, next.done, {INTERVENTION} and KhGRL's extras "
                        "(README, 'LeRobot datasets'); written to a temporary folder and renamed (required)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT if it is a "
                   "LeRobot dataset that khgrl export wrote, not the run nor any other folder (default: refuse it)")
    p.add_argument("--fps", type=int, default=None,
                   help=f"the dataset's frames per second (default: the run's --rate if > 0, else {DEFAULT_FPS})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (default: a bar on a terminal)")
    p.set_defaults(func=_cmd_export)
    return p
