"""Reading a Rerun recording back with Rerun's own API, for the view tests: its dataframe query (rerun-sdk 0.41: the
catalog API -- a local ``rerun.server.Server`` over the .rrd file, ``DatasetEntry.reader(index=...)``, a DataFusion
DataFrame; ``rerun.dataframe`` of earlier releases is gone) for the data, and ``rerun.chunk.RrdReader`` for the
recording's identity (application and recording id)."""

from __future__ import annotations

import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

# the indexes an entity's rows are read from, in this order, each entity from the first that has it: the static data
# (index None; a query on a timeline repeats it on every row), then the actor's per-step and per-episode entities
# on run_step (unique per step: a row per step, not merged across episodes as on `step` or `episode`), the
# learner's on ingested
INDEXES = (None, "run_step", "episode", "ingested")
_TIMELINES = ("episode", "step", "run_step", "ingested")


def _query(dataset, index: str | None) -> dict[str, list[dict]]:
    """entity path -> its rows (non-null values only) of a dataframe query on one index, without latest-at fill
    (none for an index the recording does not have)."""
    if index is not None and index not in {c.name for c in dataset.schema().index_columns()}:
        return {}
    table = dataset.reader(index=index, fill_latest_at=False).to_arrow_table()
    times = {n: table.column(n).to_pylist() for n in _TIMELINES if n in table.column_names}
    rows: dict[str, list[dict]] = defaultdict(list)
    by_entity: dict[str, dict[str, list]] = defaultdict(dict)
    for name in table.column_names:
        if name.startswith("/") and ":" in name:
            entity, component = name.split(":", 1)
            by_entity[entity][component] = table.column(name).to_pylist()
    for entity, cols in by_entity.items():
        for i in range(table.num_rows):
            values = {c: v[i] for c, v in cols.items() if v[i] is not None}
            if values:
                rows[entity].append({**{n: t[i] for n, t in times.items() if t[i] is not None}, **values})
    return rows


def read_rrd(path: str | Path) -> tuple[list, dict[str, list[dict]]]:
    """(recordings, entity path -> rows): each row a dict of the index columns that have a value (``episode``,
    ``step``, ``run_step``, ``ingested``, as ints) and the entity's non-null components by their column name, e.g.
    ``Points3D:positions``, as Python lists. A row the view cleared (``rr.Clear``) has no value and no row."""
    import rerun as rr
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file written by a streaming sink has no footer: read by a full scan
        recordings = RrdReader(str(path)).recordings()
        with rr.server.Server(datasets={"run": [str(path)]}) as server:
            dataset = server.client().get_dataset("run")
            rows: dict[str, list[dict]] = {}
            for index in INDEXES:
                for entity, found in _query(dataset, index).items():
                    rows.setdefault(entity, found)
    return recordings, rows


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
