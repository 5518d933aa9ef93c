"""A robot-style run in real time (``khgrl bench robot``; README, "On a real robot"): gym-hil's Panda (a MuJoCo arm
under operational-space control) stepped at wall-clock rate (``--rate``, default its own 10 Hz) in ``--mode robot``
with the safety layer on (rate limits at the arm's speed, the reset path, ``--confirm-reset``), physical corrections
(the scripted physical human pushes in episode 2), and these faults:

* before each episode the actor holds until this benchmark says ``ready`` (as a person would);
* in episode 2, the e-stop is pressed at step ``ESTOP_AT`` and released a second later;
* in episode 3, the learner is SIGKILLed at step ``KILL_AT`` and restarted with ``--resume`` ``--down`` seconds later;
* in episode 4, the link is lost: the router is SIGSTOPped at step ``LOSS_AT`` for 1.5 s; the actor, supervised by
  ``khgrl supervise``, holds once the heartbeat is ``supervision_timeout`` old, and stays held after the router is
  back until the release 2 s later;
* after the last episode, the e-stop is pressed with no actor alive and the actor restarted with ``--resume`` for
  one more episode: it reads the run's e-stop state and takes no step until the release 3 s after its first heartbeat
  (the SIGKILLed actor restarted under the e-stop: tests/integration/test_supervision.py).

A router, a learner, ``khgrl supervise`` and the actor are separate processes (as on a robot, a GPU box and the
operator's machine); this process watches every frame and the actor's status over Zenoh. Reported: the actor's loop
period (p50 / p99 / max against the target), every e-stop's delay from its command (the watchdog's: from the
timeout) to the held robot, how long the robot was held and why, what the robot did while the learner was down
(frames, the longest gap between them), the steps from the link's loss to the hold and after the router came back,
the restarted actor's frames under the e-stop, the detection of the pushes, the reset paths, and every transition in
the resumed learner's checkpoint exactly once.

    khgrl bench robot --out docs/robot_run/robot_run.json
"""

from __future__ import annotations

import json
import re
import signal
import threading
import time
from pathlib import Path

import numpy as np

__all__ = ["run_robot_benchmark", "ESTOP_AT", "KILL_AT", "LOSS_AT"]

ESTOP_AT, KILL_AT, LOSS_AT = 20, 15, 10  # steps of episodes 2, 3 and 4
HELD = re.compile(r"e-stop by (.*): robot held at episode (\d+) step (\d+), ([\d.]+) ms after the command")


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


class _Driver:
    """Says ready, presses the e-stop, kills and restarts the learner, cuts the link, restarts the actor under the
    e-stop, until the actor exits (module docstring); ``events``: what happened when."""

    def __init__(self, session, keys, watch: _Watch, procs, learner_args: list[str], actor_args: list[str],
                 down: float) -> None:
        self.session, self.keys, self.watch, self.procs = session, keys, watch, procs
        self.learner_args, self.actor_args, self.down = learner_args, actor_args, down
        self.seq, self.events, self.readied = 0, {}, set()
        self.learner = None  # the resumed learner

    def send(self, command: str) -> None:
        from khgrl.common.delivery.declare import put
        from khgrl.common.wire.control import LAUNCHER, control_payload

        put(self.session, self.keys.control("actor"), control_payload(command, LAUNCHER, self.seq), congestion="block")
        self.seq += 1

    def run(self, actor):
        """Drive the run until ``actor`` (or its restarted process) exits; the last actor process."""
        ev = self.events
        while actor.poll() is None:
            time.sleep(0.01)
            held, (episode, t) = self.watch.held, self.watch.at()
            if held.startswith("waiting for ready before episode") and int(held.split()[5]) not in self.readied:
                self.readied.add(int(held.split()[5]))
                self.send("ready")
            if episode == 2 and t >= ESTOP_AT and "estop" not in ev:
                ev["estop"] = time.monotonic()
                self.send("estop")
                time.sleep(1.0)
                self.send("release")
            if episode == 3 and t >= KILL_AT and "kill" not in ev:
                self.procs.group.procs[1].kill()  # the learner (started second): SIGKILL
                ev["kill"] = time.monotonic()
                time.sleep(self.down)
                self.learner = self.procs.start("learner-resumed", "learner", *self.learner_args, "--resume")
                ev["back"] = time.monotonic()
            if episode == 4 and t >= LOSS_AT and "loss" not in ev:
                self.link_loss()
        ev["readied"] = sorted(self.readied)
        return actor

    def link_loss(self) -> None:
        """The router SIGSTOPped for 1.5 s: steps from the loss to the hold, and after the router came back."""
        router, ev = self.procs.group.procs[0], self.events
        before = self.watch.at()
        ev["loss"] = time.monotonic()
        router.signal(signal.SIGSTOP)
        time.sleep(1.5)
        router.signal(signal.SIGCONT)
        time.sleep(1.0)
        held = self.watch.at()
        time.sleep(2.0)
        ev["loss_steps"] = held[1] - before[1] if held[0] == before[0] else None
        ev["loss_steps_after_back"] = self.watch.at()[1] - held[1] if self.watch.at()[0] == held[0] else None
        ev["loss_held"] = self.watch.held
        self.send("release")

    def restart(self, episodes: int):
        """The run done, the e-stop pressed with no actor alive, the actor restarted with ``--resume`` for one more
        episode: its frames before the release (3 s after its first heartbeat); the new actor process."""
        ev = self.events
        ev["restart"] = time.monotonic()
        self.send("estop")  # (the supervisor keeps it: RUN_DIR/estop.json and its heartbeat)
        time.sleep(0.5)
        args = list(self.actor_args)
        args[args.index("--episodes") + 1] = str(episodes + 1)
        log = Path(args[args.index("--run-dir") + 1]) / "actor-a0" / "actor.log"
        beats = log.read_text().count("supervised: first heartbeat")
        actor = self.procs.start("actor-restarted", "actor", *args, "--resume")
        deadline = time.monotonic() + 120
        while log.read_text().count("supervised: first heartbeat") <= beats and time.monotonic() < deadline:
            time.sleep(0.1)
        n = len(self.watch.frames)
        time.sleep(3.0)
        ev["restart_frames_before_release"] = len(self.watch.frames) - n
        ev["restart_held"] = self.watch.held
        self.send("release")
        return actor


def run_robot_benchmark(rate: float = 10.0, episodes: int = 4, down: float = 3.0, seed: int = 1,
                        work: str = "runs/bench-robot", out: str | None = None) -> dict:
    """The robot-style run (module docstring).

    :param rate: the control rate (Hz; gym-hil's Panda runs at 10)
    :param episodes: episodes (>= 4: the e-stop in episode 2, the learner's kill in 3, the link's loss in 4; then
        one more after the restart under the e-stop)
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

    if episodes < 4:
        raise ValueError("--episodes must be >= 4 (the e-stop is in episode 2, the learner's kill in 3, the link's "
                         "loss in 4)")
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
            actor_args = ["--run", run, "--connect", ep, "--run-dir", str(run_dir), "--id", "a0", *world, "--rate",
                          str(rate), "--episodes", str(episodes), "--human-episodes", "2", "--physical", "scripted",
                          "--confirm-reset", "--max-speed", "1"]
            driver = _Driver(session, keys, watch, procs, learner_args, actor_args, down)
            actor = driver.run(procs.start("actor", "actor", *actor_args))
            summary = json.loads((run_dir / "actor-a0" / "summary.json").read_text())  # (the restart writes its own)
            actor = driver.run(driver.restart(episodes))
            events = driver.events
            for s in subs:
                s.undeclare()
        code = actor.poll()
        driver.learner.stop(60, signal.SIGINT)  # the resumed learner: its final checkpoint
    finally:
        procs.close()
    return _report(run_dir, summary, watch, events, code, rate, down, detection, provenance_check, out)


def _report(run_dir: Path, s: dict, watch: _Watch, events: dict, code, rate: float, down: float, detection,
            provenance_check, out: str | None) -> dict:
    """The numbers of the run (``s``: the actor's summary of the episodes before the restart), printed and (``out``)
    written as JSON."""
    import csv

    with open(run_dir / "actor-a0" / "physical.csv", newline="") as fh:
        phys = detection(list(csv.DictReader(fh)))
    times = np.array([f[0] for f in watch.frames])
    k0, k1 = events.get("kill", 0.0), events.get("back", 0.0) + 1.0
    during = times[(times >= k0) & (times <= k1)]
    acct = provenance_check(run_dir)
    held = HELD.findall((run_dir / "actor-a0" / "actor.log").read_text())  # (both parts of the actor)
    res = {"rate_hz": rate, "actor_exit": code, "loop_period_ms": s["loop_period_ms"],
           "estop_latency_ms": [float(h[3]) for h in held if not h[0].startswith(("the watchdog", "the run's"))],
           "watchdog_latency_ms": [float(h[3]) for h in held if h[0].startswith("the watchdog")],
           "link_loss": {k: events.get(f"loss_{k}") for k in ("steps", "steps_after_back", "held")},
           "restart_under_estop": {"frames_before_release": events.get("restart_frames_before_release"),
                                   "held": events.get("restart_held")},
           "held_s": s["safety"]["held_s"],
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
    loss = res["link_loss"]
    print(f"link lost (router SIGSTOP 1.5 s): {loss['steps']} steps to the hold, the watchdog held "
          f"{res['watchdog_latency_ms']} ms after the {1e3 * 0.4:.0f} ms timeout; {loss['steps_after_back']} steps "
          f"after the router came back ({loss['held']!r})")
    print(f"actor restarted under the e-stop: {res['restart_under_estop']['frames_before_release']} "
          f"frames before the release ({res['restart_under_estop']['held']!r})")
    print(f"pushes: {res['physical']}; reset paths {res['reset_paths']}")
    print(f"{res['transitions']} transitions: {res['lost']} lost, {res['duplicated']} duplicated")
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(res, indent=2, default=float))
        print(f"wrote {out}")
    return res
