"""Demonstrations on disk: load and save M x N x O trajectories as NPZ or CSV.

Formats (any M, N, O; every demonstration must have the same N):

* NPZ: one array ``demos`` of shape (M, N, O) (other arrays are ignored).
* CSV: a header line then one row per sample with columns ``demo, step, y0, y1, ...`` (``demo`` and
  ``step`` integers; rows may come in any order). Lines starting with ``#`` are comments.

Time is implicit: demonstration m's step n has input s = n / (N - 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["DemoFormatError", "load_demos", "save_demos", "validate_demos"]


class DemoFormatError(ValueError):
    """A demonstration file or array is malformed (ragged, non-finite, wrong shape, ...)."""


def validate_demos(demos: np.ndarray, source: str = "demonstrations") -> np.ndarray:
    """Return ``demos`` as float64 (M, N, O), or raise :class:`DemoFormatError` saying what is wrong."""
    try:
        arr = np.asarray(demos, dtype=np.float64)
    except (ValueError, TypeError) as exc:  # ragged nested lists
        raise DemoFormatError(
            f"{source}: not a rectangular numeric array ({exc}); all demonstrations need the same length"
        ) from exc
    if arr.ndim != 3:
        raise DemoFormatError(f"{source}: expected shape (M demos, N steps, O outputs), got {arr.shape}")
    m, n, o = arr.shape
    if m < 1 or n < 2 or o < 1:
        raise DemoFormatError(f"{source}: need M >= 1 demos of N >= 2 steps and O >= 1 outputs, got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        dm, st, ax = np.argwhere(bad)[0]
        raise DemoFormatError(f"{source}: non-finite value ({arr[dm, st, ax]}) at demo {dm}, step {st}, output {ax}")
    return arr


def save_demos(path: str | Path, demos: np.ndarray) -> Path:
    """Write demonstrations to ``path`` (.npz or .csv, by suffix)."""
    path = Path(path)
    demos = validate_demos(demos)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".npz":
        np.savez_compressed(path, demos=demos)
    elif path.suffix == ".csv":
        m, n, o = demos.shape
        idx = np.indices((m, n)).reshape(2, -1).T
        table = np.concatenate([idx, demos.reshape(m * n, o)], axis=1)
        header = ",".join(["demo", "step"] + [f"y{k}" for k in range(o)])
        np.savetxt(path, table, delimiter=",", header=header, comments="", fmt=["%d", "%d"] + ["%.17g"] * o)
    else:
        raise DemoFormatError(f"{path}: unknown demonstration format {path.suffix!r} (use .npz or .csv)")
    return path


def load_demos(path: str | Path) -> np.ndarray:
    """Read demonstrations from a .npz or .csv file; returns float64 (M, N, O)."""
    path = Path(path)
    if not path.is_file():
        raise DemoFormatError(f"{path}: no such file")
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            if "demos" not in data:
                raise DemoFormatError(f"{path}: NPZ has no 'demos' array (found {list(data.keys())})")
            return validate_demos(data["demos"], str(path))
    if path.suffix == ".csv":
        return _load_csv(path)
    raise DemoFormatError(f"{path}: unknown demonstration format {path.suffix!r} (use .npz or .csv)")


def _load_csv(path: Path) -> np.ndarray:
    lines = [ln.strip() for ln in path.read_text().splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    if not lines:
        raise DemoFormatError(f"{path}: empty CSV")
    names = tuple(c.strip() for c in lines[0].split(","))
    if len(names) < 3 or names[0] != "demo" or names[1] != "step":
        raise DemoFormatError(f"{path}: CSV header must be 'demo,step,y0,...', got {','.join(names)}")
    try:
        rows = [[float(v) for v in ln.split(",")] for ln in lines[1:]]
    except ValueError as exc:
        raise DemoFormatError(f"{path}: non-numeric value ({exc})") from exc
    if not rows or any(len(r) != len(names) for r in rows):
        raise DemoFormatError(f"{path}: every row needs {len(names)} columns ({','.join(names)})")
    cols = np.asarray(rows, dtype=np.float64)
    if np.isnan(cols[:, :2]).any():
        raise DemoFormatError(f"{path}: missing or non-numeric demo/step index")
    demo_ids = cols[:, 0].astype(np.int64)
    steps = cols[:, 1].astype(np.int64)
    uniq = np.unique(demo_ids)
    lengths = {int(d): int(np.sum(demo_ids == d)) for d in uniq}
    if len(set(lengths.values())) != 1:
        raise DemoFormatError(
            f"{path}: ragged demonstrations (steps per demo: {lengths}); all must have the same length"
        )
    m, n, o = len(uniq), next(iter(lengths.values())), cols.shape[1] - 2
    demos = np.empty((m, n, o))
    for k, d in enumerate(uniq):
        rows = demo_ids == d
        order = np.argsort(steps[rows])
        if not np.array_equal(steps[rows][order], np.arange(n)):
            raise DemoFormatError(f"{path}: demo {d} steps must be 0..{n - 1} exactly once")
        demos[k] = cols[rows][order, 2:]
    return validate_demos(demos, str(path))
