"""Issue 21, the ``human-user`` and ``monitor`` attacks: one ``khgrl up --secure`` run (robot mode at 20 Hz, so the
actor's rate is its own, not the learner's), attacked in turn from sessions holding the run's own ``human-user`` and
``monitor`` certificates -- what those roles may publish and query under access control:

1. P_h = (1e300, -1e300) on every frame for 3 s: refused (counted ``rejects.correction``), never applied, and L is
   not refitted (no ``scale`` message), where the old actor projected it and refitted L (15 -> 87.8).
2. a hold on every frame for 15 s: with ``--human-hold-s 2`` (refilled 0.5 s per second not held) a0's steps are
   intervened at most (2 + 0.5 * 15) / 1.5 = 6.3 s of them (the old actor: every step, 11 s or more of the 15 even
   with a path back to the start between two episodes in the window, which is not a step).
3. lock-step words one step ahead for 8 s: each even frame t answered with a word for step t + 2, so step t + 1 never
   has its word. The actor gives the client up at once (its word for a later step came first) and backs off, so it
   never waits the correction timeout and keeps its 20 Hz (the old actor re-entered lock-step with each word and
   waited the 0.5 s timeout every other step: 9 Hz instead of 20 in the issue's measurement).
4. 1,000 ``get learner/weights`` a second for 6 s from the ``monitor``: the learner answers at most its reply budget
   (the old one answered every query); its gradient steps/s during the flood against before it are printed (this
   test's own process sends the flood, on the same cores: ``khgrl bench queries`` measures it from a separate
   process, docs/attacks.md).
5. a pause (``human/user/request``) that is never renewed, with ``--human-pause-s 3``: the actor resumes by itself
   and the run ends by itself (the old actor stayed paused: the run hung).

Then: exit code 0, not stopped, the learner alive to the end with its memory under 1 GB, and the honest actor's
transitions exactly once (0 lost, 0 duplicated) in the learner's final checkpoint.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from test_secure import _session

from helpers import read_json, wait_for
from launch import FAST, Launcher

pytestmark = pytest.mark.integration

RATE = 20.0
HOLD_S = 15.0  # 2.: how long the client holds every frame
ARGS = [*FAST, "--method", "khgrl", "--human", "none", "--episodes", "7", "--seed", "5", "--mode", "robot",
        "--rate", str(RATE), "--human-hold-s", "2", "--human-hold-refill", "0.5", "--human-pause-s", "3", "--secure",
        # the supervisor's heartbeat is test_supervision's subject, not this test's: in the full suite the flood this
        # test's own process sends (4.) once kept the launcher's heartbeat away 0.85 s on the shared 2 cores, the
        # watchdog latched the e-stop (as it must) and a0 stayed held through 5.
        "--supervision-timeout", "10"]


class Watch:
    """What the run shows a monitor: a0's frames, its scale messages and the learner's status, with arrival times."""

    def __init__(self, session, keys) -> None:
        from khgrl.common.wire.messages import Frame
        from khgrl.common.wire.protocol import ProtocolError, Status, decode

        self.frames: list[tuple[float, object]] = []
        self.scales: list[float] = []
        self.learner: list[tuple[float, object]] = []
        self.lock = threading.Lock()

        def on_frame(s) -> None:
            try:
                f = decode(Frame, s.payload.to_bytes())
            except ProtocolError:
                return
            with self.lock:
                self.frames.append((time.monotonic(), f))

        def on_status(s) -> None:
            try:
                st = decode(Status, s.payload.to_bytes())
            except ProtocolError:
                return
            self.learner.append((time.monotonic(), st.info))

        self.subs = [session.declare_subscriber(keys.frame("a0"), on_frame),
                     session.declare_subscriber(keys.scale("a0"), lambda s: self.scales.append(time.monotonic())),
                     session.declare_subscriber(keys.status("learner", "*"), on_status)]

    def since(self, t0: float) -> list:
        with self.lock:
            return [f for t, f in self.frames if t >= t0]

    def between(self, t0: float, t1: float) -> list:
        with self.lock:
            return [f for t, f in self.frames if t0 <= t < t1]

    @staticmethod
    def steps(frames: list) -> list[tuple[object, float]]:
        """(frame, seconds to the next frame) for consecutive frames of one episode: the path back to the start
        between two episodes is not a step (no frames), and a window that spans it is not slower for it."""
        return [(a, b.envelope.ts - a.envelope.ts) for a, b in zip(frames, frames[1:]) if a.episode == b.episode]

    def rate(self, t0: float, t1: float) -> float:
        """Steps/s between t0 and t1, by the actor's own timestamps, within episodes (:meth:`steps`)."""
        gaps = [g for _, g in self.steps(self.between(t0, t1))]
        return len(gaps) / sum(gaps) if gaps and sum(gaps) > 0 else 0.0

    def held(self, t0: float, t1: float) -> tuple[float, float]:
        """(seconds a0's steps were intervened, seconds it stepped) between t0 and t1, within episodes."""
        steps = self.steps(self.between(t0, t1))
        return sum(g for f, g in steps if f.intervening), sum(g for _, g in steps)

    def gaps(self, t0: float, n: int) -> list[float]:
        """The seconds between a0's consecutive steps of one episode, in its first ``n`` frames from t0."""
        return [g for _, g in self.steps(self.since(t0)[:n])]

    def grad_rate(self, t0: float, t1: float) -> float | None:
        pts = [(t, i.gradient_steps) for t, i in self.learner if t0 <= t <= t1]
        return (pts[-1][1] - pts[0][1]) / (pts[-1][0] - pts[0][0]) if len(pts) > 1 else None


def _answer_frames(watch: Watch, seconds: float, answer) -> tuple[float, float]:
    """Answer every new frame of a0 for ``seconds`` with ``answer(frame)``; returns (start, end)."""
    t0 = time.monotonic()
    seen = 0
    while time.monotonic() - t0 < seconds:
        frames = watch.since(t0)
        for f in frames[seen:]:
            answer(f)
        seen = len(frames)
        time.sleep(0.002)
    return t0, time.monotonic()


def _flood_queries(session, key: str, qps: float, count: int, seconds: float) -> tuple[int, list[int]]:
    """Send ``count`` queries at up to ``qps`` (a loaded machine sends them slower), giving up after ``seconds``."""
    got = [0]
    t0, n = time.monotonic(), 0
    while n < count and time.monotonic() - t0 < seconds:
        session.get(key, lambda r: got.__setitem__(0, got[0] + (r.ok is not None)), timeout=2.0)
        n += 1
        delay = t0 + n / qps - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    return n, got


def _held(up: Launcher) -> str:
    """The actor's last holds and releases, for a failure's message."""
    log = (up.run_dir / "actor-a0" / "actor.log").read_text().splitlines()
    return "\n".join([line for line in log if "held" in line or "released" in line][-8:])


@pytest.mark.timeout(600)
def test_human_and_monitor_attacks_are_bounded(tmp_path):
    from khgrl.common.delivery.control_auth import ControlSigner
    from khgrl.common.delivery.learner_link import QUERY_BURST, QUERY_RATE
    from khgrl.common.wire.messages import Correction
    from khgrl.common.wire.protocol import Keys, encode

    up = Launcher(tmp_path, tmp_path / "run", *ARGS)
    report: dict = {}
    try:
        up.wait_line("[a0] episode 1:", 300)
        runtime = read_json(up.run_dir / "config.json")["runtime"]
        keys, ep = Keys(runtime["run"]), runtime["endpoint"]
        monitor, human = _session(up.run_dir, "monitor", ep), _session(up.run_dir, "human-user", ep)
        try:
            watch = Watch(monitor, keys)
            pub = human.declare_publisher(keys.correction("user"))
            seq = iter(range(10**6))

            def send(active: bool, p_h=None, episode=None, t=None, step=None) -> None:
                msg = Correction(client="user", actor="a0", active=active,
                                 p_h=None if p_h is None else np.asarray(p_h, float), episode=episode, t=t, step=step)
                pub.put(encode(msg, "user", next(seq)))

            # the quiet rate once a0 steps again: after episode 1 its reset path (not a transition: no frames) may
            # take seconds, and in CI a fixed 6 s sleep once fell entirely within it (0.0 steps/s)
            q0 = wait_for(lambda: watch.frames and watch.frames[0][0], 60, "a0's frames after episode 1")
            time.sleep(5.0)
            quiet_rate, quiet_grad = watch.rate(q0, time.monotonic()), watch.grad_rate(q0, time.monotonic())
            assert quiet_rate > 0.8 * RATE, f"a0 runs at {quiet_rate:.1f} steps/s before any attack\n{_held(up)}"

            # 1. P_h far outside the workspace
            t0, t1 = _answer_frames(watch, 3.0, lambda f: send(True, (1e300, -1e300), f.episode, f.t))
            send(False)
            time.sleep(1.5)
            far = watch.since(t0)
            assert not any(f.intervening for f in far), "a P_h of 1e300 drove the robot"
            assert not [t for t in watch.scales if t >= t0], "a P_h of 1e300 refitted L"

            # 2. a hold on every frame
            t0, t1 = _answer_frames(watch, HOLD_S, lambda f: send(True, f.mean + 0.01, f.episode, f.t))
            send(False)
            held_s, stepping_s = watch.held(t0, t1)
            bound = (2.0 + 0.5 * (t1 - t0)) / 1.5  # the allowance: 2 s when full, refilled 0.5 s per second not held
            report.update(held_s=round(held_s, 2), stepping_s=round(stepping_s, 2), held_bound_s=round(bound, 2))
            # (stepping long enough that an actor held at every step would exceed the bound)
            assert stepping_s > bound + 1.0, f"a0 stepped {stepping_s:.1f} s of {t1 - t0:.1f}\n{_held(up)}"
            assert 1.0 < held_s <= bound + 0.5, f"one client held a0 {held_s:.1f} s of {stepping_s:.1f} s stepping"

            # 3. lock-step words one step ahead
            time.sleep(1.0)
            t0, t1 = _answer_frames(watch, 8.0, lambda f: f.t % 2 or send(True, f.mean, f.episode, f.t, step=f.t + 2))
            send(False)
            lock_rate = watch.rate(t0, t1)
            waits = sum(g > 0.4 for g in watch.gaps(t0, int(8 * RATE)))  # the correction timeout is 0.5 s
            report.update(lockstep_rate=round(lock_rate, 2), lockstep_waits=waits)
            assert waits <= 1, f"a0 waited the correction timeout {waits} times for a client one step ahead"
            assert lock_rate > 0.9 * quiet_rate, f"a0 at {lock_rate:.1f} steps/s (was {quiet_rate:.1f})"

            # 4. weights query flood from the monitor
            t0 = time.monotonic()
            n, answered = _flood_queries(monitor, keys.weights, 1000.0, 4000, 20.0)
            t1 = time.monotonic()
            time.sleep(2.5)
            flood_grad = watch.grad_rate(t0, t1)
            report.update(queries=n, answered=answered[0], grad_quiet=quiet_grad, grad_flood=flood_grad)
            assert n > 3000, f"the flood sent only {n} queries"
            assert answered[0] <= QUERY_RATE * (t1 - t0 + 2.5) + QUERY_BURST, f"{answered[0]} of {n} answered"
            if quiet_grad and flood_grad:
                report["grad_ratio"] = round(flood_grad / quiet_grad, 3)

            # 5. a pause never renewed
            user = ControlSigner.load(up.run_dir, "human:user")  # the client's own key (khgrl up makes one for it)
            human.put(keys.human_request("user"), user.payload(keys.human_request("user"), "pause", "user", 0))
            t0 = time.monotonic()
            time.sleep(2.0)
            assert len(watch.since(t0 + 0.5)) <= 2, "the pause did not pause a0"
            deadline = time.monotonic() + 10.0
            while not watch.since(t0 + 2.0) and time.monotonic() < deadline:
                time.sleep(0.1)
            assert watch.since(t0 + 2.0), "a0 stayed paused: the pause never expired"
            rss = max(i.rss_mb for _, i in watch.learner)
            for s in watch.subs:
                s.undeclare()
        finally:
            monitor.close()
            human.close()
        rc = up.proc.wait(timeout=300)
        assert rc == 0, f"khgrl up exited {rc}\n{up.stdout[-3000:]}\n{up.stderr[-3000:]}"
    finally:
        up.cleanup()
    print("attack results:", report)
    summary = read_json(up.run_dir / "summary.json")
    assert summary["stopped_by"] is None and not summary["failed"], summary
    a0 = read_json(up.run_dir / "actor-a0" / "summary.json")
    c = a0["corrections"]
    assert c["far_outside"] > 0 and a0["rejects"].get("correction", 0) >= c["far_outside"], a0["rejects"]
    assert c["holds_expired"] >= 1 and c["holds_refused"] > 0, c
    assert c["lockstep_skipped"] >= 1 and c["lockstep_timeouts"] <= 3, c  # given up at once, backing off
    log = (up.run_dir / "logs" / "a0.log").read_text()
    assert "pause of human-input client 'user' expired" in log
    assert rss < 1024, f"learner RSS {rss:.0f} MB"
    from khgrl.benchmarks.scale import provenance_check

    acct = provenance_check(up.run_dir)
    assert acct["lost"] == 0 and acct["duplicated"] == 0 and acct["produced"] > 0, acct
