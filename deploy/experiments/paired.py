"""Two evaluations of the same policies on the same scenes, side by side: ``python -m
khgrl.deploy.experiments.paired --a TRUE.csv ... --b CAMERA.csv ... --names true camera``.

Each pair of ``khgrl eval --scenes`` CSVs (one run evaluated twice with the same ``--seed``: the same scenes, e.g.
``--task panda:pick`` and ``--task panda:pick-camera``) gives, per run and pooled: each side's success with its
Wilson 95 % interval, the discordant scenes (one side succeeds, the other fails) with McNemar's exact two-sided p
(the binomial test of the discordant pairs), and where the CSVs hold the same placement columns, the distance
between the two sides' placements per scene (for the camera: the estimate's error, in the placement's units).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
from khgrl.deploy.tools.intervals import rate_text

__all__ = ["mcnemar_exact", "compare_pair", "main"]

RESULT_COLUMNS = {"scene", "seed", "varies", "success", "return", "env_return", "action_cost", "steps", "terminated"}


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p of ``b`` and ``c`` discordant pairs (binomial, p = 1/2).

    :param b: pairs where only the first side succeeds.
    :param c: pairs where only the second side succeeds.
    """
    n = b + c
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(b, c) + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or "success" not in rows[0] or "seed" not in rows[0]:
        raise ValueError(f"{path}: not a khgrl eval --scenes CSV")
    return rows


def compare_pair(a: Path, b: Path) -> dict:
    """The comparison of two per-scene CSVs of the same scenes.

    :param a: the first side's CSV.
    :param b: the second side's.
    :raises ValueError: the files are not of the same scenes.
    """
    ra, rb = _rows(a), _rows(b)
    if [r["seed"] for r in ra] != [r["seed"] for r in rb]:
        raise ValueError(f"{a} and {b} are not of the same scenes (their seeds differ): evaluate with one --seed")
    sa = np.array([r["success"] == "True" for r in ra])
    sb = np.array([r["success"] == "True" for r in rb])
    only_a, only_b = int(np.sum(sa & ~sb)), int(np.sum(~sa & sb))
    out = {"a": str(a), "b": str(b), "scenes": len(ra), "a_successes": int(sa.sum()), "b_successes": int(sb.sum()),
           "only_a": only_a, "only_b": only_b, "mcnemar_p": mcnemar_exact(only_a, only_b)}
    place = [k for k in ra[0] if k not in RESULT_COLUMNS and k in rb[0]]
    if place:
        pa = np.array([[float(r[k]) for k in place] for r in ra])
        pb = np.array([[float(r[k]) for k in place] for r in rb])
        dist = np.linalg.norm(pa - pb, axis=1)
        out["placement"] = place
        out["distance"] = {"mean": float(dist.mean()), "p95": float(np.percentile(dist, 95)), "max": float(dist.max()),
                           "per_scene": [float(d) for d in dist]}
    return out


def report(pairs: list[dict], names: tuple[str, str]) -> str:
    """A markdown table: one row per pair and the pooled row."""
    head = (f"| pair | {names[0]} | {names[1]} | only {names[0]} | only {names[1]} | McNemar p | "
            f"placement distance mean / p95 / max |\n|---|---|---|---|---|---|---|")
    rows = [head]
    for i, p in enumerate([*pairs, _pool(pairs)]):
        label = "pooled" if i == len(pairs) else Path(p["a"]).stem
        d = p.get("distance")
        dist = f"{d['mean']:.4g} / {d['p95']:.4g} / {d['max']:.4g}" if d else "-"
        rows.append(f"| {label} | {rate_text(p['a_successes'], p['scenes'])} | "
                    f"{rate_text(p['b_successes'], p['scenes'])} | {p['only_a']} | {p['only_b']} | "
                    f"{p['mcnemar_p']:.3g} | {dist} |")
    return "\n".join(rows)


def _pool(pairs: list[dict]) -> dict:
    keys = ("scenes", "a_successes", "b_successes", "only_a", "only_b")
    out = {k: sum(p[k] for p in pairs) for k in keys}
    out["mcnemar_p"] = mcnemar_exact(out["only_a"], out["only_b"])
    dists = [d for p in pairs for d in p.get("distance", {}).get("per_scene", [])]
    if dists:
        arr = np.array(dists)
        out["distance"] = {"mean": float(arr.mean()), "p95": float(np.percentile(arr, 95)), "max": float(arr.max())}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m khgrl.deploy.experiments.paired", description=__doc__.split("\n\n")[0])
    p.add_argument("--a", nargs="+", required=True, type=Path, help="the first side's scenes CSVs")
    p.add_argument("--b", nargs="+", required=True, type=Path, help="the second side's, in the same order")
    p.add_argument("--names", nargs=2, default=("a", "b"), help="the two sides' names (default: a b)")
    p.add_argument("--out", type=Path, default=None, help="write the comparison as JSON here (default: none)")
    args = p.parse_args(argv)
    if len(args.a) != len(args.b):
        print("paired: error: give as many --b files as --a files", file=sys.stderr)
        return 2
    try:
        pairs = [compare_pair(a, b) for a, b in zip(args.a, args.b)]
    except (OSError, ValueError) as exc:
        print(f"paired: error: {exc}", file=sys.stderr)
        return 2
    print(report(pairs, tuple(args.names)))
    if args.out is not None:
        args.out.write_text(json.dumps({"names": list(args.names), "pairs": pairs, "pooled": _pool(pairs)}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
