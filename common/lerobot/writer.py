"""Write a LeRobot dataset (format v3.0) with LeRobot's own writer, all or nothing.

``LeRobotDataset.create`` in a temporary folder beside the output, ``add_frame`` per frame, ``save_episode`` per
episode, ``finalize``; then the folder is renamed into place (an existing output is replaced only with
``overwrite``, only if it is a dataset KhGRL wrote (:func:`not_a_dataset`), and only once the new one is complete).
A failure, Ctrl-C included, removes the temporary folder: nothing half-written is left at the output.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from khgrl.common.lerobot.library import lerobot_dataset_class, quiet

__all__ = ["Episode", "write_dataset", "not_a_dataset", "SIDECAR"]

SIDECAR = "meta/khgrl.json"  # provenance beside LeRobot's own meta/info.json (which has no field for it)
DATASET_ENTRIES = frozenset({"meta", "data", "videos", "images"})  # what a LeRobot v3.0 dataset folder holds


@dataclass
class Episode:
    """One episode to write.

    :param task: its task string (LeRobot's per-frame ``task``).
    :param columns: feature name -> (F, *shape) array in the feature's dtype, F frames.
    """

    task: str
    columns: dict[str, np.ndarray]

    @property
    def frames(self) -> int:
        """F, the number of frames."""
        return len(next(iter(self.columns.values())))


def not_a_dataset(out: Path) -> str:
    """Why the existing folder ``out`` is not a LeRobot dataset that KhGRL wrote ("" when it is one: LeRobot's
    ``meta/info.json`` and KhGRL's ``meta/khgrl.json``, and nothing beside LeRobot's own folders), so that
    ``--overwrite`` replaces nothing else.

    :param out: an existing path.
    """
    if out.is_symlink() or not out.is_dir():
        return "it is not a folder"
    missing = [m for m in ("meta/info.json", SIDECAR) if not (out / m).is_file()]
    if missing:
        return f"it has no {' and no '.join(missing)}"
    other = sorted(p.name for p in out.iterdir() if p.name not in DATASET_ENTRIES)
    return f"it holds {', '.join(other[:5])}{' ...' if len(other) > 5 else ''} besides the dataset" if other else ""


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists: give --overwrite to replace it, or another output folder")
    if (out.exists() or out.is_symlink()) and (why := not_a_dataset(out)):
        raise FileExistsError(f"{out} is not a LeRobot dataset that khgrl export wrote ({why}): not replaced; "
                              f"give another output folder")


def write_dataset(out: str | Path, *, fps: int, features: dict, episodes: Iterable[Episode], overwrite: bool = False,
                  sidecar: dict | None = None, on_episode: Callable[[Episode], None] | None = None) -> Path:
    """Write ``episodes`` as the LeRobot dataset folder ``out``; returns its path.

    :param out: the dataset folder to write.
    :param fps: frames per second (LeRobot's ``fps``: frame k of an episode has timestamp k / fps).
    :param features: LeRobot's feature dict (``{name: {"dtype", "shape", "names"}}``).
    :param episodes: the episodes, each a non-empty :class:`Episode`.
    :param overwrite: replace an existing ``out``.
    :param sidecar: written as JSON to ``out/meta/khgrl.json`` (provenance).
    :param on_episode: called after each episode is saved (progress).
    :raises FileExistsError: ``out`` exists and not ``overwrite``.
    :raises ValueError: no episodes, or a frame the library refuses (its message).
    """
    out = Path(out)
    _check_out(out, overwrite)
    dataset_class = lerobot_dataset_class()
    quiet()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    ds = None
    try:
        ds = dataset_class.create(repo_id=f"local/{out.name}", fps=int(fps), features=features, root=tmp,
                                  use_videos=False, video_backend="pyav")
        count = 0
        for ep in episodes:
            for i in range(ep.frames):
                ds.add_frame({**{k: v[i] for k, v in ep.columns.items()}, "task": ep.task})
            with warnings.catch_warnings():  # its statistics histogram a bool feature as uint8, and says so
                warnings.filterwarnings("ignore", "Converting input from bool", RuntimeWarning)
                ds.save_episode()
            count += 1
            if on_episode is not None:
                on_episode(ep)
        ds.finalize()
        if count == 0:
            raise ValueError(f"{out}: no episodes to write")
        if sidecar is not None:
            (tmp / SIDECAR).write_text(json.dumps(sidecar, indent=2) + "\n")
        _move_into_place(tmp, out)
    except BaseException:
        _discard(ds, tmp)
        raise
    return out


def _discard(ds, tmp: Path) -> None:
    """Remove a failed write: close the library's writers first (closing flushes its buffered episode metadata,
    which would otherwise land in the folder after it is removed)."""
    if ds is not None:
        try:
            ds.finalize()
        except Exception:  # noqa: BLE001 - the write failed already; its own error is the one raised
            pass
    shutil.rmtree(tmp, ignore_errors=True)


def _move_into_place(tmp: Path, out: Path) -> None:
    old = out.parent / f".{out.name}.replaced-{os.getpid()}"
    if out.exists():
        os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)
