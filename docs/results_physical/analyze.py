"""Tables of docs/results_physical.md from the runs of run.sh: per run, success, the human's steps, and the
physical detector against the scripted pushes (precision / recall per step, delay in steps, detections in episodes
without a push).

    python docs/results_physical/analyze.py runs/physical --out docs/results_physical
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from khgrl.actor.physical import detection

HUMAN = (4, 5, 10, 19, 20)


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def one(run: Path) -> dict:
    """One run's numbers."""
    eps = _rows(run / "actor-a0" / "episodes.csv")
    auto = [e for e in eps if int(e["episode"]) not in HUMAN]
    ok = [int(e["episode"]) for e in auto if e["success"] == "True"]
    out = {"run": run.name, "arm": run.name.split("-")[1], "seed": int(run.name.rsplit("seed", 1)[1]),
           "last10": sum(e["success"] == "True" for e in eps[-10:]) / 10,
           "first_autonomous_success": min(ok) if ok else None,
           "human_steps": sum(int(e["intervention_steps"]) for e in eps),
           "human_episode_successes": sum(e["success"] == "True" for e in eps if int(e["episode"]) in HUMAN)}
    phys = run / "actor-a0" / "physical.csv"
    if phys.is_file():
        d = detection(_rows(phys))
        out.update(precision=d["precision"], recall=d["recall"], recall_without_contact=d["recall_without_contact"],
                   delays=d["delay_steps"],
                   false_quiet=d["false_in_quiet_episodes"], quiet=d["quiet_episodes"], pushed=d["pushed"])
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("runs", type=Path)
    p.add_argument("--out", type=Path, default=Path("docs/results_physical"))
    p.add_argument("--overwrite", action="store_true", help="replace an existing per_run.json")
    args = p.parse_args()
    rows = [one(r) for r in sorted(args.runs.glob("panda_pick-*-seed*")) if (r / "actor-a0" / "episodes.csv").is_file()]
    if args.out.joinpath("per_run.json").is_file() and not args.overwrite:
        raise SystemExit(f"{args.out / 'per_run.json'} exists: --overwrite to replace it")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "per_run.json").write_text(json.dumps(rows, indent=2, default=float))
    for r in rows:
        print(json.dumps(r, default=float))


if __name__ == "__main__":
    main()
