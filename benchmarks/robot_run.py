"""A robot-style run in real time (``khgrl bench robot``; README, "On a real robot"): gym-hil's Panda (a MuJoCo arm
under operational-space control) stepped at wall-clock rate (``--rate``, default its own 10 Hz) in ``--mode robot``
with the safety layer on (rate limits at the arm's speed, the reset path, ``--confirm-reset``), physical corrections
(the scripted physical human pushes in episode 2), and three faults while it runs:

* before each episode the actor holds until this benchmark says ``ready`` (as a person would);
* in episode 2, the e-stop is pressed at step ``ESTOP_AT`` and released a second later;
* in episode 3, the learner is SIGKILLed at step ``KILL_AT`` and restarted with ``--resume`` ``--down`` seconds later.

A router, a learner and the actor are separate processes (as on a robot and a GPU box); this process watches every
frame and the actor's status over Zenoh. Reported: the actor's loop period (p50 / p99 / max against the target),
the e-stop's delay from the command to the held robot, how long the robot was held and why, what the robot did
while the learner was down (frames, the longest gap between them), the detection of the pushes, the reset paths,
and every transition in the resumed learner's checkpoint exactly once.

    khgrl bench robot --out docs/robot_run/robot_run.json
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import numpy as np

__all__ = ["run_robot_benchmark", "ESTOP_AT", "KILL_AT"]

ESTOP_AT, KILL_AT = 20, 15  # steps of episodes 2 and 3


class _Watch:
    """Frames (arrival, episode, t) and the actor's latest ``held`` (a Zenoh thread writes)."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, int, int]] = []
        self.held = ""
        self.lock = threading.Lock()

    def on_frame(self, sample) -> None:
        from khgrl.common.wire.protocol import Frame, ProtocolError, decode

        try:
            f = decode(Frame, sample.payload.to_bytes())
        except ProtocolError:
            return
        with self.lock:
            self.frames.append((time.monotonic(), f.episode, f.t))

    def on_status(self, sample) -> None:
        from khgrl.common.wire.protocol import ProtocolError, Status, decode

        try:
            st = decode(Status, sample.payload.to_bytes())
        except ProtocolError:
            return
        if st.role == "actor":
            with self.lock:
                self.held = st.info.held

    def at(self) -> tuple[int, int]:
        with self.lock:
            return self.frames[-1][1:] if self.frames else (0, -1)


def _drive(session, keys, watch: _Watch, procs, learner_args: list[str], actor, down: float) -> dict:
    """Say ready, press the e-stop, kill and restart the learner, until the actor exits; what happened when."""
    from khgrl.common.delivery.declare import put
    from khgrl.common.wire.control import LAUNCHER, control_payload

    seq, events, readied = 0, {}, set()

    def send(command: str) -> None:
        nonlocal seq
        put(session, keys.control("actor"), control_payload(command, LAUNCHER, seq), congestion="block")
        seq += 1

    while actor.poll() is None:
        time.sleep(0.01)
        held, (episode, t) = watch.held, watch.at()
        if held.startswith("waiting for ready before episode"):
            n = int(held.split()[5])
            if n not in readied:
                readied.add(n)
                send("ready")
        if episode == 2 and t >= ESTOP_AT and "estop" not in events:
            events["estop"] = time.monotonic()
            send("estop")
            time.sleep(1.0)
            send("release")
        if episode == 3 and t >= KILL_AT and "kill" not in events:
            procs.group.procs[1].kill()  # the learner (started second): SIGKILL
            events["kill"] = time.monotonic()
            time.sleep(down)
            procs.start("learner-resumed", "learner", *learner_args, "--resume")
            events["back"] = time.monotonic()
    events["readied"] = sorted(readied)
    return events


def run_robot_benchmark(rate: float = 10.0, episodes: int = 4, down: float = 3.0, seed: int = 1,
                        work: str = "runs/bench-robot", out: str | None = None) -> dict:
    """The robot-style run (module docstring).

    :param rate: the control rate (Hz; gym-hil's Panda runs at 10)
    :param episodes: episodes (>= 3: the e-stop is in episode 2, the learner's kill in episode 3)
    :param down: seconds the learner stays dead
    :param seed: seed of the run
    :param work: run directory
    :param out: also write the results as JSON here
    """
    from khgrl.actor.physical import detection
    from khgrl.benchmarks.runtime.procs import BenchProcs, run_id, task_file
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys

    if episodes < 3:
        raise ValueError("--episodes must be >= 3 (the e-stop is in episode 2, the learner's kill in episode 3)")
    work_dir = Path(work).resolve()
    run = run_id("robot")
    run_dir = work_dir / run
    procs, watch = BenchProcs(work_dir), _Watch()
    both = ["--mode", "robot", "--seed", str(seed), "--learning-starts", "64"]
    world = ["--task", "panda:pick", "--no-adapt", *both]
    task_file(run_dir, {"task": "panda:pick", "adapt": False})
    try:
        ep = procs.router()
        learner_args = ["--run", run, "--connect", ep, "--run-dir", str(run_dir), "--id", "learner", *both]
        procs.start("learner", "learner", *learner_args)
        procs.supervise(run, ep, run_dir)  # (robot mode: the actor moves only while supervised)
        keys = Keys(run)
        with open_client(ep, timeout=30) as session:
            subs = [session.declare_subscriber(keys.frame("a0"), watch.on_frame),
                    session.declare_subscriber(keys.status("actor", "a0"), watch.on_status)]
            actor = procs.actor("actor", run, ep, run_dir, *world, "--rate", str(rate), "--episodes", str(episodes),
                                "--human-episodes", "2", "--physical", "scripted", "--confirm-reset",
                                "--max-speed", "1")
            events = _drive(session, keys, watch, procs, learner_args, actor, down)
            for s in subs:
                s.undeclare()
        code = actor.poll()
        procs.group.procs[-1].stop(60, signal.SIGINT)  # the resumed learner: its final checkpoint
    finally:
        procs.close()
    return _report(run_dir, watch, events, code, rate, down, detection, provenance_check, out)


def _report(run_dir: Path, watch: _Watch, events: dict, code, rate: float, down: float, detection,
            provenance_check, out: str | None) -> dict:
    """The numbers of the run, printed and (``out``) written as JSON."""
    import csv

    s = json.loads((run_dir / "actor-a0" / "summary.json").read_text())
    with open(run_dir / "actor-a0" / "physical.csv", newline="") as fh:
        phys = detection(list(csv.DictReader(fh)))
    times = np.array([f[0] for f in watch.frames])
    k0, k1 = events.get("kill", 0.0), events.get("back", 0.0) + 1.0
    during = times[(times >= k0) & (times <= k1)]
    acct = provenance_check(run_dir)
    res = {"rate_hz": rate, "actor_exit": code, "loop_period_ms": s["loop_period_ms"],
           "estop_latency_ms": s["safety"]["estop_latency_ms"], "held_s": s["safety"]["held_s"],
           "safety_counts": {k: v for k, v in s["safety"].items() if isinstance(v, int)},
           "reset_paths": s["safety"]["reset_paths"], "readied": events.get("readied"),
           "learner_down_s": round(events.get("back", 0.0) - k0, 2),
           "frames_while_learner_down": int(during.size),
           "longest_frame_gap_while_learner_down_s": float(np.max(np.diff(during))) if during.size > 1 else None,
           "physical": {k: phys[k] for k in ("pushed", "detected", "precision", "recall", "delay_steps",
                                             "false_in_quiet_episodes")},
           "transitions": s["transitions"], "lost": acct["lost"], "duplicated": acct["duplicated"]}
    p = res["loop_period_ms"]
    print(f"loop period p50 {p['p50']:.1f} ms, p99 {p['p99']:.1f} ms, max {p['max']:.1f} ms (target {p['target']:.0f})")
    print(f"e-stop: held {res['estop_latency_ms']} ms after the command; held {res['held_s']} s")
    print(f"learner down {res['learner_down_s']} s: {res['frames_while_learner_down']} frames meanwhile, longest gap "
          f"{res['longest_frame_gap_while_learner_down_s']} s (robot mode: the robot acts on with its weights)")
    print(f"pushes: {res['physical']}; reset paths {res['reset_paths']}")
    print(f"{res['transitions']} transitions: {res['lost']} lost, {res['duplicated']} duplicated")
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(res, indent=2, default=float))
        print(f"wrote {out}")
    return res
