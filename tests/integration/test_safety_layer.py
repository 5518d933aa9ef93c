"""The actor's safety layer with real processes (``actor/safety.py``, ``common/tasks/safety.py``, ``khgrl stop``).

One ``khgrl up`` of the passage world at 20 Hz with ``--rate-limit on --reset-path on --confirm-reset`` (no
scripted human), watched by this test's own Zenoh session (every frame and status). Before each episode the actor
holds until ``khgrl ready RUN_DIR`` (no frame before it; a thread of this test says ready when the status asks), and
before the second it first drives the robot back to the start within the rate limits. The run goes through three
faults:

1. ``khgrl stop RUN_DIR --now``: the actor holds within one control period (the delay from the command's timestamp to
   its first held period, measured by the actor), no frame comes while it holds, the status says ``e-stop by
   launcher``; ``--release`` lets it go on.
2. A live human-input client (a real process publishing plain corrections to a far corner every 50 ms) holds the
   robot and is SIGKILLed: the robot is held (no step) for ``correction_timeout - human_silence_s``, the status says
   which client is silent, then the policy drives again -- through the rate limit, no jump.
3. The learner is SIGSTOPped (simulation mode: the actor waits for it): the watchdog holds the robot and says
   ``waiting for the learner`` until SIGCONT.
4. The actor itself is SIGSTOPped for 0.4 s (a stalled control loop): the late step is counted, and the next P_t
   does not jump.

Throughout, no two consecutive frames' P_t differ by more than the speed limit on any axis, even while the human
drags to the far corner (the step the human asked for is many times larger), and nothing is lost.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from helpers import read_json, wait_for
from launch import FAST, UP, Launcher, _env

pytestmark = pytest.mark.integration

RATE = 20.0
ARGS = [*FAST, "--method", "khgrl", "--human", "none", "--episodes", "2", "--seed", "4", "--rate", str(RATE),
        "--rate-limit", "on", "--reset-path", "on", "--confirm-reset"]
FAR = (0.95, 0.95)
HUMAN = """
import sys, time
import numpy as np
from khgrl.common.delivery.transport import open_client
from khgrl.common.wire.messages import Correction
from khgrl.common.wire.protocol import Keys, encode
endpoint, run = sys.argv[1:3]
with open_client(endpoint, timeout=10) as s:
    key, seq = Keys(run).correction("t"), 0
    while True:
        s.put(key, encode(Correction(client="t", actor="a0", active=True, p_h=np.array(%r)), "t", seq))
        seq += 1
        if seq == 5:
            print("holding", flush=True)
        time.sleep(0.05)
""" % (FAR,)


class Watch:
    """Every frame (arrival time, episode, t, desired) and actor status (arrival time, held) of the run."""

    def __init__(self, endpoint: str, run: str) -> None:
        from khgrl.common.delivery.transport import open_client
        from khgrl.common.wire.protocol import Keys

        self.frames: list[tuple[float, int, int, np.ndarray, bool]] = []
        self.held: list[tuple[float, str]] = []
        self.lock = threading.Lock()
        self.session = open_client(endpoint, timeout=10)
        keys = Keys(run)
        self.subs = [self.session.declare_subscriber(keys.frame("a0"), self._frame),
                     self.session.declare_subscriber(keys.status("actor", "a0"), self._status)]

    def _frame(self, sample) -> None:
        from khgrl.common.wire.messages import Frame
        from khgrl.common.wire.protocol import decode

        f = decode(Frame, sample.payload.to_bytes())
        with self.lock:
            self.frames.append((time.time(), f.episode, f.t, np.asarray(f.desired), bool(f.intervening)))

    def _status(self, sample) -> None:
        from khgrl.common.wire.messages import Status
        from khgrl.common.wire.protocol import decode

        s = decode(Status, sample.payload.to_bytes())
        with self.lock:
            self.held.append((time.time(), s.info.held))

    def frames_between(self, t0: float, t1: float) -> int:
        with self.lock:
            return sum(t0 <= f[0] <= t1 for f in self.frames)

    def said(self, text: str, since: float = 0.0) -> bool:
        with self.lock:
            return any(text in h for t, h in self.held if t >= since)

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def _say_ready(up: Launcher, watch: Watch, done: threading.Event, answered: list[tuple[int, float, int]]) -> None:
    """Answer each ``waiting for ready before episode N`` once with ``khgrl ready`` (N, when, frames before)."""
    while not done.is_set():
        with watch.lock:
            asked = [int(h.split()[5]) for _, h in watch.held if h.startswith("waiting for ready before episode")]
        for n in sorted(set(asked) - {a[0] for a in answered}):
            answered.append((n, time.time(), len(watch.frames)))
            ready = _khgrl("ready", str(up.run_dir))
            assert ready.returncode == 0 and "a0: ready" in ready.stdout, ready.stdout + ready.stderr
        done.wait(0.1)


def _khgrl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*UP[:-1], *args], env=_env(), capture_output=True, text=True, timeout=60)


def _gap(watch: Watch, after: float) -> float:
    """The longest time between consecutive frames that arrived after ``after``."""
    with watch.lock:
        times = [f[0] for f in watch.frames if f[0] >= after]
    return max(np.diff(times), default=0.0)


def _estop(up: Launcher, watch: Watch) -> None:
    press = _khgrl("stop", str(up.run_dir), "--now")
    assert press.returncode == 0 and "a0: held by the e-stop" in press.stdout, press.stdout + press.stderr
    t_held = time.time()
    time.sleep(1.5)
    assert watch.frames_between(t_held, time.time()) == 0, "the actor stepped during the e-stop"
    assert watch.said("e-stop by launcher", t_held - 2.0)
    release = _khgrl("stop", str(up.run_dir), "--release")
    assert release.returncode == 0 and "a0: released" in release.stdout, release.stdout + release.stderr
    wait_for(lambda: watch.frames_between(time.time() - 0.5, time.time()) > 3, 10, "frames after the release")


def _silent_human(up: Launcher, watch: Watch, runtime: dict) -> float:
    human = subprocess.Popen([sys.executable, "-c", HUMAN, runtime["endpoint"], runtime["run"]], env=_env(),
                             stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert human.stdout.readline().strip() == "holding"
        wait_for(lambda: any(f[4] for f in watch.frames[-5:]), 10, "the human's hold in the frames")
        time.sleep(1.0)
    finally:
        human.kill()  # SIGKILL mid-hold
        human.wait(10)
    killed = time.time()
    wait_for(lambda: watch.said("human client t silent", killed), 10, "the status naming the silent client")
    wait_for(lambda: watch.frames_between(time.time() - 0.5, time.time()) > 3, 10, "frames after the release")
    return killed


def _stopped_learner(up: Launcher, watch: Watch) -> float:
    pid = read_json(up.run_dir / "pids.json")["children"]["learner"]
    os.kill(pid, signal.SIGSTOP)
    stopped = time.time()
    try:
        wait_for(lambda: watch.said("waiting for the learner", stopped), 15, "the status saying the robot waits")
        t_held = time.time()
        time.sleep(1.0)
        assert watch.frames_between(t_held, time.time()) == 0, "the actor stepped without the learner"
    finally:
        os.kill(pid, signal.SIGCONT)
    return t_held


@pytest.mark.timeout(300)
def test_estop_watchdog_and_rate_limit_hold_a_real_actor(tmp_path):
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.delta import largest_step
    from khgrl.common.tasks.world import build_task_world

    up = Launcher(tmp_path, tmp_path / "run", *ARGS)
    watch, done, answered = None, threading.Event(), []
    try:
        wait_for(lambda: (up.run_dir / "config.json").exists() and up.proc.poll() is None, 60, "config.json")
        runtime = read_json(up.run_dir / "config.json")["runtime"]
        watch = Watch(runtime["endpoint"], runtime["run"])
        threading.Thread(target=_say_ready, args=(up, watch, done, answered), daemon=True).start()
        wait_for(lambda: len(watch.frames) > 40, 90, "the actor's frames")
        _estop(up, watch)
        killed = _silent_human(up, watch, runtime)
        _stopped_learner(up, watch)
        actor = read_json(up.run_dir / "pids.json")["children"]["a0"]
        wait_for(lambda: watch.frames_between(time.time() - 0.3, time.time()) > 3, 10, "steps after SIGCONT")
        os.kill(actor, signal.SIGSTOP)  # the control loop stalls for 8 periods
        time.sleep(0.4)
        os.kill(actor, signal.SIGCONT)
        rc = up.proc.wait(timeout=200)
        assert rc == 0, f"khgrl up exited {rc}\n{up.stdout}\n{up.stderr}"
    finally:
        done.set()
        if watch is not None:
            watch.close()
        up.cleanup()
    assert [a[0] for a in answered] == [1, 2] and answered[0][2] == 0, answered  # no step before the first ready
    s = read_json(up.run_dir / "actor-a0" / "summary.json")["safety"]
    period_ms = 1e3 / RATE
    print(f"e-stop latency {s['estop_latency_ms']} ms (period {period_ms:.0f} ms); held {s['held_s']} s")
    assert s["estops"] == 1 and s["estop_latency_ms"][0] <= period_ms + 10.0, s  # (+10 ms: a loaded CI machine)
    assert s["human_silence_holds"] >= 1 and s["learner_holds"] >= 1, s
    silence = s["held_s"]["human"]  # from human_silence_s (0.3) to correction_timeout (0.5) of silence
    assert 0.1 <= silence <= 0.45, s
    assert s["held_s"]["learner"] >= 1.0 and s["held_s"]["estop"] >= 1.5 and s["held_s"]["ready"] > 0, s
    assert _gap(watch, killed) >= 0.1  # no step while the silent human's hold was frozen
    assert s["late_steps"] >= 1 and s["late_ms_max"] >= 300, s  # the stalled loop's step was late and counted

    world = build_task_world(load_task("passage:low_cov"))
    limit = 2.0 * largest_step(world.demos)
    frames = sorted((f[1], f[2], tuple(f[3]), f[4]) for f in watch.frames)
    steps = [np.max(np.abs(np.subtract(b[2], a[2]))) for a, b in zip(frames, frames[1:])
             if b[:2] == (a[0], a[1] + 1)]
    assert len(steps) > 100 and max(steps) <= limit + 1e-9, (max(steps), limit)
    dragged = [b for a, b in zip(frames, frames[1:]) if b[3] and b[:2] == (a[0], a[1] + 1)]
    assert len(dragged) >= 15, "the human held the robot for a second"
    (path,) = s["reset_paths"]  # back to the start before episode 2, within the limits
    assert path["episode"] == 2 and path["steps"] > 0 and path["max_step"] <= limit + 1e-9, path
    rows = (up.run_dir / "actor-a0" / "episodes.csv").read_text().splitlines()
    assert int(rows[1].split(",")[rows[0].split(",").index("rate_limited_steps")]) > 0
    acct = provenance_check(up.run_dir)
    assert acct["lost"] == 0 and acct["duplicated"] == 0, acct
