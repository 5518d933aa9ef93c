"""``khgrl view RUN_DIR [--out FILE.rrd] [--overwrite]``: a finished run in Rerun, from its records.

    khgrl view runs/demo --out demo.rrd     # write a recording (an existing file needs --overwrite)
    khgrl view runs/demo                    # open Rerun's viewer on it (needs a display)

What it reads: each actor's steps (``RUN_DIR/actor-ID/steps/episode-N.npz``, :func:`~khgrl.common.step_records.
read_steps`), its ``episodes.csv`` (return and success per episode), the learner's ``learner/tb/progress.csv`` (if
present) and the run's configuration (the task: demonstrations, workspace and shapes). It logs them through the
same :class:`~khgrl.common.rerun_log.RunLogger` as the live view of ``khgrl up --view``, so the entities and
timelines are the same (listed in :mod:`khgrl.common.rerun_log`); the recording id is the run id. A camera task's
images (what the policy saw, kept in the step records) are logged at every step under ``/actor/ID/images/KEY``; the
simulator's own camera exists only in a live recording (it is not kept in the run's records). The learner's
``progress.csv`` numbers (``version``, ``n_updates``, losses) go to ``/learner/...`` on the ``ingested`` timeline.

Exit codes: 0 written (or the viewer opened), 2 a bad run directory or output file, no Rerun SDK.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from pathlib import Path
from typing import Any

from khgrl.common.rerun_log import RunLogger, blueprint, has_display, import_rerun, open_recording
from khgrl.common.step_records import actor_dirs, image_keys, images_of, read_steps
from khgrl.deploy.run.rundir import still_running

__all__ = ["main", "build_parser", "log_run", "episode_results"]

_ROW = ("t", "robot", "desired", "mean", "scale", "p_h", "intervened")  # what RunLogger.step reads of a step
_LEARNER_COLUMNS = {"learner/version": "version", "train/n_updates": "n_updates", "train/critic_loss": "critic_loss",
                    "train/actor_loss": "actor_loss", "train/ent_coef": "ent_coef"}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl view", description="A finished run's records as a Rerun recording "
                                "(the entities of khgrl up --view): write an .rrd, or open the viewer on it.")
    p.add_argument("run_dir", metavar="RUN_DIR", help="the run directory (khgrl up --run-dir)")
    p.add_argument("--out", default=None, metavar="FILE.rrd",
                   help="write the recording into FILE.rrd (default: none: spawn Rerun's viewer on it)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file (default: off: refused)")
    return p


def episode_results(actor_dir: Path) -> dict[int, tuple[float, bool]]:
    """episode -> (return, success) from ``RUN_DIR/actor-ID/episodes.csv`` (empty without the file).

    :param actor_dir: ``RUN_DIR/actor-ID``.
    """
    path = Path(actor_dir) / "episodes.csv"
    if not path.is_file():
        return {}
    with open(path, newline="") as fh:
        return {int(r["episode"]): (float(r["ret"]), r["success"].strip().lower() == "true")
                for r in csv.DictReader(fh)}


def _learner_rows(run_dir: Path) -> list[dict[str, str]]:
    path = run_dir / "learner" / "tb" / "progress.csv"
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _number(text: str | None) -> float | None:
    try:
        v = float(text) if text not in (None, "") else None
    except ValueError:
        return None
    return v if v is not None and math.isfinite(v) else None


def log_run(run_dir: Path, rec: Any, world: Any) -> dict[str, int]:
    """Log a run's records into ``rec``; returns counts (actors, episodes, steps, learner rows).

    :param run_dir: the run directory.
    :param rec: a ``rerun.RecordingStream``.
    :param world: the run's :class:`~khgrl.common.tasks.world.TaskWorld` (its demonstrations, workspace, shapes).
    """
    counts = {"actors": 0, "episodes": 0, "steps": 0, "learner_rows": 0}
    actors = actor_dirs(run_dir)
    keys = next((k for _, d in actors if (k := image_keys(d))), ())
    rec.send_blueprint(blueprint([actor for actor, _ in actors], camera=False, images=keys))
    for actor, actor_dir in actors:
        logger = RunLogger(rec, actor)
        logger.scene(world.demos, (world.low, world.high), tuple(world.view.shapes))
        results = episode_results(actor_dir)
        for arrays in read_steps(actor_dir):
            ep = int(arrays["episode"])
            scene = {k: arrays[k] for k in ("kmp_mean", "kmp_projector", "via")}
            logger.start(ep, scene)
            proj = arrays["kmp_projector"]
            images = images_of(arrays)
            for i in range(len(arrays["t"])):
                row = {k: arrays[k][i] for k in _ROW}
                logger.step(ep, row, proj[min(int(row["t"]), len(proj) - 1)])
                for key, frames in images.items():
                    logger.image(ep, int(row["t"]), frames[i], entity=f"images/{key}")
            ret, success = results.get(ep, (float(arrays["reward"].sum()), bool(arrays["terminated"][-1:].any())))
            logger.finish(ep, arrays, ret, success)
            counts["episodes"] += 1
            counts["steps"] += len(arrays["t"])
        counts["actors"] += 1
    learner = RunLogger(rec, "learner")
    for row in _learner_rows(run_dir):
        ingested = _number(row.get("learner/ingested"))
        if ingested is not None:
            learner.learner(int(ingested), {name: _number(row.get(col)) for col, name in _LEARNER_COLUMNS.items()})
            counts["learner_rows"] += 1
    return counts


def _world(run_dir: Path) -> tuple[Any, str]:
    from khgrl.common.tasks.world import build_task_world
    from khgrl.deploy.tools.eval_inputs import load_run_task, read_config

    cfg, runtime, _ = read_config(run_dir)
    task, _ = load_run_task(cfg, runtime.get("cwd"))
    return build_task_world(task), str(runtime.get("run") or run_dir.name)


def _check(args: argparse.Namespace) -> tuple[Path, Path | None]:
    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir} is not a directory")
    if running := still_running(run_dir, "khgrl view"):
        raise ValueError(running)
    if not any(run_dir.glob("actor-*/steps/episode-*.npz")):
        raise ValueError(f"{run_dir}: no step records (RUN_DIR/actor-ID/steps/episode-N.npz: a run of this version "
                         f"of khgrl up keeps them for each finished episode)")
    out = None if args.out is None else Path(args.out)
    if out is not None:
        if out.suffix != ".rrd":
            raise ValueError(f"--out {out}: the recording file must end in .rrd")
        if not out.parent.is_dir():
            raise ValueError(f"--out {out}: no such folder {out.parent} (make it first)")
        if out.exists() and not args.overwrite:
            raise ValueError(f"--out {out} exists: give --overwrite to replace it, or another file")
    elif not has_display():
        raise ValueError("no display for Rerun's viewer: write a file with --out FILE.rrd (then: rerun FILE.rrd)")
    return run_dir, out


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        run_dir, out = _check(args)
        import_rerun()
        world, run_id = _world(run_dir)
    except (ValueError, ImportError, RuntimeError, FileNotFoundError) as exc:
        print(f"khgrl view: error: {exc}", file=sys.stderr)
        return 2
    if out is not None:
        out.unlink(missing_ok=True)
        tmp = out.with_name(out.name + ".part")
        rec = open_recording(run_id, save=str(tmp))
    else:
        rec = open_recording(run_id)
        rec.spawn()
    counts = log_run(run_dir, rec, world)
    rec.flush()
    rec.disconnect()
    if out is not None:
        os.replace(tmp, out)
    where = out if out is not None else "Rerun's viewer"
    print(f"khgrl view: {counts['actors']} actor(s), {counts['episodes']} episodes, {counts['steps']} steps, "
          f"{counts['learner_rows']} learner rows -> {where}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
