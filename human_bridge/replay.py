"""``khgrl human replay FILE``: feed a recorded correction session into a new run.

The actor records every correction it applies to ``RUN_DIR/actor-ID/corrections.csv`` (one row per intervened
step: run, actor, episode, step, time, client, P_h, projected, clipped; see ``actor.service.CorrectionRecord``).
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
import queue
import time
from pathlib import Path

import numpy as np

from common.protocol import Keys, ProtocolError, RejectCounter, decode, encode

__all__ = ["load_record", "ReplayPlan", "add_parser", "run_replay"]


def load_record(path: str | Path) -> list[dict]:
    """Rows of a corrections.csv (or .jsonl), typed: episode, step (int), p_h (2,), actor, client."""
    path = Path(path)
    rows = []
    if path.suffix == ".jsonl":
        import json

        raw = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    else:
        with open(path, newline="") as fh:
            raw = list(csv.DictReader(fh))
    for r in raw:
        p_h = r["p_h"] if "p_h" in r else [r["p_h_x"], r["p_h_y"]]
        p = np.array([float(v) for v in p_h], dtype=np.float64)
        if p.shape != (2,) or not np.all(np.isfinite(p)):
            raise ValueError(f"{path}: bad p_h in row {r}")
        rows.append({"actor": str(r["actor"]), "episode": int(r["episode"]), "step": int(r["step"]), "p_h": p,
                     "client": str(r.get("client", ""))})
    return rows


class ReplayPlan:
    """What to send for each frame: P_h for (episode, t + 1) if recorded, else a release."""

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


def run_replay(args: argparse.Namespace) -> int:
    from common.session import StopFlag, install_stop_handlers, open_client
    from human_bridge.service import CorrectionPublisher

    plan = ReplayPlan(load_record(args.file), args.from_actor)
    target = args.actor or plan.source
    keys = Keys(args.run)
    flag = StopFlag()
    install_stop_handlers(flag)
    rejects = RejectCounter(f"human/{args.id}")
    inbox: queue.Queue = queue.Queue(maxsize=4096)

    def cb(kind):
        return lambda s: inbox.put((kind, str(s.key_expr), s.payload.to_bytes()))

    print(f"khgrl human replay ({args.id}): {len(plan.steps)} corrected steps of actor {plan.source} from {args.file} "
          f"-> actor {target}, last at episode {plan.last[0]} step {plan.last[1]}", flush=True)
    sent_steps = 0
    with open_client(args.connect) as session:
        subs = [session.declare_subscriber(keys.frame(target), cb("frame")),
                session.declare_subscriber(keys.control("human"), cb("control")),
                session.declare_subscriber(keys.control("all"), cb("control"))]
        token = session.liveliness().declare_token(keys.alive("human", args.id))
        pub = CorrectionPublisher(session, keys, args.id)
        deadline = time.monotonic() + args.wait
        got_frame = False
        announced: set[int] = set()
        try:
            while not flag:
                try:
                    kind, key, payload = inbox.get(timeout=0.2)
                except queue.Empty:
                    if not got_frame and time.monotonic() > deadline:
                        print(f"khgrl human replay: no frame from actor {target} within {args.wait} s", flush=True)
                        return 1
                    continue
                try:
                    msg = decode(kind, payload)
                except ProtocolError as exc:
                    rejects.reject(kind, key, exc)
                    continue
                if kind == "control":
                    if msg["command"] == "stop":
                        flag.set("stop command")
                    continue
                got_frame = True
                ep, t = msg["episode"], msg["t"]
                p_h = plan.correction(ep, t)
                if ep + 1 in plan.episodes and ep + 1 not in announced:
                    announced.add(ep + 1)  # announce lock-step for the next episode with its step 0's word
                    pub.send(target, plan.steps.get((ep + 1, 0)), ep + 1, t, step=0)
                if ep in plan.episodes:
                    pub.send(target, p_h, ep, t, step=t + 1)  # step-addressed: the actor waits for it
                else:
                    pub.send(target, None, ep, t)  # releases a hold, if any
                sent_steps += p_h is not None
                if plan.finished(ep, t) and p_h is None and not pub.active.get(target, False):
                    break
        finally:
            for actor, active in list(pub.active.items()):
                if active:
                    pub.send(actor, None)
            pub.close()
            for s in subs:
                s.undeclare()
            token.undeclare()
    print(f"khgrl human replay: sent {sent_steps} corrections for recorded steps, {pub.sent} messages, "
          f"{rejects.total} rejected", flush=True)
    return 0


def add_parser(sub, default_endpoint: str) -> argparse.ArgumentParser:
    p = sub.add_parser("replay", help="feed a recorded corrections.csv into a new run at the same episodes and steps")
    p.add_argument("file", help="RUN_DIR/actor-ID/corrections.csv of the recorded run (or .jsonl)")
    p.add_argument("--run", required=True, help="run id of the new run")
    p.add_argument("--connect", default=default_endpoint, help="router endpoint (default %(default)s)")
    p.add_argument("--from-actor", default=None, help="which recorded actor's rows to replay (default: the first)")
    p.add_argument("--actor", default=None, help="actor to drive (default: the recorded actor's id)")
    p.add_argument("--id", default="replay", help="client id")
    p.add_argument("--wait", type=float, default=120.0, help="give up if no frame arrives within this many seconds")
    p.add_argument("--scenario", default=None, help=argparse.SUPPRESS)
    p.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--episodes", type=int, nargs="+", default=None, help=argparse.SUPPRESS)
    p.add_argument("--run-dir", default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run_replay)
    return p
