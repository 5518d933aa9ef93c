"""Soak (not collected by pytest; minutes): N actors at the default lead cap (``--max-lead 8`` on both sides), the
learner SIGKILLed K times -- each time once it is up and its journal has grown by 80 transitions -- and resumed with
``--resume``. Lost and duplicated transitions are counted three ways: the learner's provenance in its final
checkpoint, the actors' summaries (unconfirmed transitions), and a wire tap (the transition indices each actor
published, against the rows the learner holds).

    .venv/bin/python tests/soak_resume.py WORK_DIR [--actors 8] [--kills 8] [--episodes 2]

Exit 0 when every count is 0 and every process ended with 0.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from helpers import ProcGroup, read_json, unique_run, wait_for  # noqa: E402


def _stored(run_dir: Path) -> dict[str, set[int]]:
    """Per actor id: the transition indices in the final checkpoint's replay buffer."""
    from khgrl.learner.checkpoint import find_checkpoint, load_checkpoint_arrays

    ck = find_checkpoint(run_dir / "learner")
    arrays, state = load_checkpoint_arrays(ck), json.loads((ck / "state.json").read_text())
    return {a: set(arrays["provenance_step"][arrays["provenance_actor"] == int(s["code"])].tolist())
            for a, s in state["actors"].items()}


def soak(work: Path, actors: int, kills: int, episodes: int) -> dict:
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys, Transitions, decode
    from khgrl.learner.journal_scan import read_records

    run, run_dir = unique_run("soak"), work / "run"
    learner_args = ["--learning-starts", "64", "--max-lead", "8"]
    tapped: dict[str, set[int]] = {}

    def on_batch(sample) -> None:
        m = decode(Transitions, sample.payload.to_bytes())
        tapped.setdefault(m.actor, set()).update(range(m.first_step, m.first_step + m.n))

    def journaled() -> int:
        return sum(m.n for m in read_records(run_dir / "learner" / "journal"))

    t0 = time.monotonic()
    with ProcGroup(work) as g:
        ep = g.router()
        learner = g.learner(run, ep, *learner_args)
        with open_client(ep) as s:
            sub = s.declare_subscriber(Keys(run).transitions("*"), on_batch)
            procs = [g.actor(run, ep, "--scenario", "low_cov", "--method", "kgrl", "--learning-starts", "64",
                             "--max-lead", "8", "--episodes", str(episodes), "--id", f"a{i}",
                             "--flush-timeout", "1200") for i in range(actors)]
            done = 0
            while done < kills and any(p.poll() is None for p in procs):
                wait_for(lambda: "ready (epoch" in learner.text(), 180, "the learner ready", procs=[learner])
                before = journaled()
                wait_for(lambda: journaled() >= before + 80 or all(p.poll() is not None for p in procs), 600,
                         "80 more transitions in the journal", procs=[learner])
                time.sleep(1.0)
                learner.kill()
                learner.wait(30)
                done += 1
                print(f"{time.monotonic() - t0:.0f} s: kill {done} ({journaled()} transitions in the journal)",
                      flush=True)
                learner = g.learner(run, ep, *learner_args, "--resume")
            codes = [p.wait(1300) for p in procs]
            time.sleep(2.0)
            sub.undeclare()
        rc = learner.stop(120)
    summaries = [read_json(run_dir / f"actor-a{i}" / "summary.json") for i in range(actors)]
    stored = _stored(run_dir)
    made = {f"a{i}": set(range(s["next_index"])) for i, s in enumerate(summaries)}
    return {"kills": done, "wall_s": round(time.monotonic() - t0), "actor_exit_codes": codes, "learner_exit": rc,
            "provenance": provenance_check(run_dir),
            "actors_unconfirmed": sum(s["unconfirmed_transitions"] for s in summaries),
            "tap_not_published": sum(len(made[a] - tapped.get(a, set())) for a in made),
            "tap_vs_stored_differ": sum(len(stored.get(a, set()) ^ tapped.get(a, set())) for a in made)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("work", type=Path, help="work directory (created)")
    p.add_argument("--actors", type=int, default=8, help="actors (default: %(default)s)")
    p.add_argument("--kills", type=int, default=8, help="learner SIGKILLs (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=2, help="episodes per actor (default: %(default)s)")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    res = soak(args.work, args.actors, args.kills, args.episodes)
    print(json.dumps(res))
    counts = (res["provenance"]["lost"], res["provenance"]["duplicated"], res["actors_unconfirmed"],
              res["tap_not_published"], res["tap_vs_stored_differ"], res["learner_exit"], *res["actor_exit_codes"])
    return 0 if res["kills"] == args.kills and not any(counts) else 1


if __name__ == "__main__":
    sys.exit(main())
