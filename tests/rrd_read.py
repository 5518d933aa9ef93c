"""Reading a Rerun recording back with Rerun's own API (rerun-sdk 0.41: ``rerun.chunk.RrdReader``; the older
``rerun.dataframe`` query API is gone and its successor needs the ``datafusion`` extra), for the view tests."""

from __future__ import annotations

import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np


def read_rrd(path: str | Path) -> tuple[list, dict[str, list[dict]]]:
    """(recordings, entity path -> rows): each row a dict of the chunk's columns (index columns ``episode``,
    ``step``, ``run_step``, ``ingested`` as ints where present; components by their column name, e.g.
    ``Points3D:positions``, as Python lists; None where a row has no value, e.g. a Clear)."""
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file written by a streaming sink has no footer: read by a full scan
        reader = RrdReader(str(path))
        recordings = reader.recordings()
        rows: dict[str, list[dict]] = defaultdict(list)
        for chunk in reader.stream():
            batch = chunk.to_record_batch()
            names = [n for n in batch.schema.names if n not in ("log_time",) and not n.startswith("rerun.controls")]
            cols = {n: batch.column(n).to_pylist() for n in names}
            for i in range(batch.num_rows):
                rows[chunk.entity_path].append({n: cols[n][i] for n in names})
    return recordings, dict(rows)


def by_step(rows: list[dict], column: str) -> dict[tuple[int, int], np.ndarray]:
    """(episode, step) -> the first instance's value of ``column`` (rows without a value skipped)."""
    out = {}
    for r in rows:
        v = r.get(column)
        if v:
            out[(int(r["episode"]), int(r["step"]))] = np.asarray(v[0], dtype=np.float64)
    return out


def by_episode(rows: list[dict], column: str = "Scalars:scalars") -> dict[int, float]:
    """episode -> the scalar logged for it."""
    return {int(r["episode"]): float(r[column][0]) for r in rows if r.get(column)}
