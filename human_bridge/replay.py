"""``khgrl human replay FILE``: feed a recorded correction session into a new run.

The actor records every correction it applies to ``RUN_DIR/actor-ID/corrections.csv`` (one row per intervened
step: run, actor, episode, step, time, client, P_h, projected, clipped).
This client watches the new run's frames and, in every episode that has recorded corrections, answers the frame
of step (episode, t) with a step-addressed correction for step t + 1: the P_h recorded for (episode, t + 1), or a
release when that step was not corrected. The actor waits for that word before taking the step (lock-step, see
docs/protocol.md), so the replay lands on the recorded steps whatever the latency or control rate. With the same
seeds (and a deterministic policy, e.g. still in its random warm-up) the new run then intervenes at exactly the
recorded episodes and steps.

While the episode before a recorded one runs, the client announces lock-step for the recorded episode with its
word for step 0 (a hold carried over the boundary is replayed too). Limit: a recorded episode 1 has no episode
before it, so lock-step starts with the first word that reaches the actor in time.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np
from khgrl.common.config.process import ProcessConfig
from khgrl.common.process import StopFlag, install_stop_handlers
from khgrl.common.wire.protocol import Frame
from khgrl.human_bridge.client import CorrectionPublisher, connected

__all__ = ["load_record", "ReplayPlan", "ReplayAnswers", "add_arguments", "run"]


def load_record(path: str | Path) -> list[dict]:
    """Rows of a corrections.csv (or .jsonl), typed: episode, step (int), p_h (O,), actor, client.

    :param path: the record file.
    """
    path = Path(path)
    rows = []
    if path.suffix == ".jsonl":
        raw = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    else:
        with open(path, newline="") as fh:
            raw = list(csv.DictReader(fh))
    for r in raw:
        p_h = r["p_h"] if "p_h" in r else [v for k, v in r.items() if k.startswith("p_h_")]
        p = np.array([float(v) for v in p_h], dtype=np.float64)
        if p.ndim != 1 or not 1 <= p.size <= 64 or not np.all(np.isfinite(p)):
            raise ValueError(f"{path}: bad p_h in row {r}")
        rows.append({"actor": str(r["actor"]), "episode": int(r["episode"]), "step": int(r["step"]), "p_h": p,
                     "client": str(r.get("client", ""))})
    return rows


class ReplayPlan:
    """What to send for each frame: P_h for (episode, t + 1) if recorded, else a release.

    :param rows: the record's rows (:func:`load_record`).
    :param actor: whose rows to replay (default: the first recorded actor).
    """

    def __init__(self, rows: list[dict], actor: str | None = None) -> None:
        actors = sorted({r["actor"] for r in rows})
        if actor is None:
            actor = actors[0] if actors else "a0"
        self.source = actor
        self.steps = {(r["episode"], r["step"]): r["p_h"] for r in rows if r["actor"] == actor}
        self.last = max(self.steps) if self.steps else (0, -1)
        self.episodes = {ep for ep, _ in self.steps}

    def correction(self, episode: int, t: int) -> np.ndarray | None:
        return self.steps.get((episode, t + 1))

    def finished(self, episode: int, t: int) -> bool:
        return (episode, t) >= self.last


class ReplayAnswers:
    """The replay client's answer to each frame of the driven actor.

    :param plan: the recorded corrections.
    :param pub: the correction stream to publish on.
    :param target: the actor to drive.
    """

    def __init__(self, plan: ReplayPlan, pub: CorrectionPublisher, target: str) -> None:
        self.plan, self.pub, self.target = plan, pub, target
        self.announced: set[int] = set()
        self.sent_steps = 0

    def frame(self, f: Frame) -> bool:
        """Answer the frame of step (episode, t); True once the record is done and nothing is held.

        :param f: the driven actor's frame.
        """
        ep, t = f.episode, f.t
        p_h = self.plan.correction(ep, t)
        if ep + 1 in self.plan.episodes and ep + 1 not in self.announced:
            self.announced.add(ep + 1)  # announce lock-step for the next episode with its step 0's word
            self.pub.send(self.target, self.plan.steps.get((ep + 1, 0)), ep + 1, t, step=0)
        if ep in self.plan.episodes:
            self.pub.send(self.target, p_h, ep, t, step=t + 1)  # step-addressed: the actor waits for it
        else:
            self.pub.send(self.target, None, ep, t)  # releases a hold, if any
        self.sent_steps += p_h is not None
        return self.plan.finished(ep, t) and p_h is None and not self.pub.active.get(self.target, False)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The replay client's own flags."""
    parser.add_argument("file", nargs="?", default=None,
                        help="RUN_DIR/actor-ID/corrections.csv of the recorded run (or .jsonl; default: the run "
                             "setting replay, as khgrl up --human replay --replay FILE starts it)")
    parser.add_argument("--from-actor", default=None, help="which recorded actor's rows to replay (default: the first)")
    parser.add_argument("--actor", default=None, help="actor to drive (default: the recorded actor's id)")
    parser.add_argument("--id", default="replay", help="client id (default: %(default)s)")
    parser.add_argument("--wait", type=float, default=120.0,
                        help="give up if no frame arrives within this many seconds (default: %(default)s)")


def run(args: argparse.Namespace, proc: ProcessConfig) -> int:
    """``khgrl human replay FILE``: exit 0 once the record is replayed, 1 if no frame came within ``--wait``.

    :param args: the parsed command line (:func:`add_arguments`).
    :param proc: the resolved run settings (run id, endpoint, scenario, seed, human_episodes, human_noise).
    """
    args.file = args.file or proc.cfg.replay
    if not args.file:
        print("khgrl human replay: error: no record to replay: give FILE or --replay FILE", file=sys.stderr, flush=True)
        return 2
    try:
        plan = ReplayPlan(load_record(args.file), args.from_actor)
    except (OSError, ValueError, KeyError) as exc:
        print(f"khgrl human replay: cannot read {args.file}: {exc}", file=sys.stderr, flush=True)
        return 2
    target = args.actor or plan.source
    flag = StopFlag()
    install_stop_handlers(flag)
    print(f"khgrl human replay ({args.id}): {len(plan.steps)} corrected steps of actor {plan.source} from {args.file} "
          f"-> actor {target}, last at episode {plan.last[0]} step {plan.last[1]}", flush=True)
    try:
        with connected(proc, args.id, flag, target) as link:
            answers = ReplayAnswers(plan, link.pub, target)
            deadline = time.monotonic() + args.wait
            while not flag:
                got = link.next(timeout=0.2)
                link.publish_status()
                if got is not None and answers.frame(got[1]):
                    break
                if link.frames == 0 and time.monotonic() > deadline:
                    print(f"khgrl human replay: no frame from actor {target} within {args.wait} s", flush=True)
                    return 1
    except ConnectionError as exc:
        if flag:
            return 0
        print(f"khgrl human replay: {exc}", file=sys.stderr, flush=True)
        return 1
    print(f"khgrl human replay: sent {answers.sent_steps} corrections for recorded steps, {link.pub.sent} messages, "
          f"{link.rejects.total} rejected", flush=True)
    return 0
