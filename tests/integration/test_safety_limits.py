"""Exact limits after every hold, and the e-stop over the wait for a lock-step word (issue 33, defects 4 and 5), with
real processes and every command the robot's driver gets; and the live run is not overwritten (defect 8).

One ``khgrl up`` of the passage world behind a driver that logs each command (``tests/driver_log_task.py``) at 20 Hz
with ``--rate-limit on --reset-path on``, the scripted human in lock-step in episode 1, and a correction timeout of
3 s. Simulation mode, so that every kind of hold happens (a robot does not wait for the learner). While it runs,
``khgrl up --overwrite`` on its directory must be refused, ``khgrl ready`` must say that nothing waited, and
``khgrl export``, ``view`` and ``eval`` must refuse the live run. Then the test drives:

1. the scripted human SIGSTOPped: the actor waits for its word; then ``khgrl stop --now``. The e-stop must hold the
   robot at once, not after the wait (which goes on after the release, until the actor gives up on the client).
   Before the fix the actor went on waiting for the full correction timeout, took the step, and only then held:
   the delay to the hold was ~2.5 s, and the step the e-stop caught was sent before the release.
2. the e-stop with a hand on the arm: the robot moved by :data:`~driver_log_task.PUSH` while held; after the release
   the commands start from where it was measured (before the fix: from the position last sent, 6 d away).
3. a live human-input client dragging to a far corner, SIGKILLed (the silent-human freeze).
4. the learner SIGSTOPped (the wait for the learner).
5. the actor SIGSTOPped for 0.4 s (a stalled loop).
6. the end of episode 1: the path back to the start goes on from the last step's velocity.

Every position the driver got is then checked against both limits, as it got them: a step of at most the speed
limit from the previous position sent -- or, after a hold or a reset, from where the robot was measured -- and a
change of step of at most the acceleration limit, the velocity being zero after any hold or reset. Before the fix
the velocity went on through every hold (a first step from standstill of up to 2 d, four times the acceleration
limit) and the reset path started "from rest" while the robot moved (steps changing by 1.5-2.5 d).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import REPO, read_json, wait_for
from launch import FAST, UP, Launcher, _env

pytestmark = pytest.mark.integration

RATE, TIMEOUT = 20.0, 3.0
ARGS = [*FAST, "--task", "driver_log_task:make_task", "--method", "khgrl", "--human", "scripted",
        "--human-episodes", "1", "--episodes", "3", "--seed", "4", "--rate", str(RATE), "--rate-limit", "on",
        "--reset-path", "on", "--correction-timeout", str(TIMEOUT),
        "--net-arch", "256", "256", "--batch-size", "256",  # the default sizes: the seeded episodes this test's
        # faults are timed against (with FAST's small networks the scripted human still holds when the dying client
        # drags); a lease longer than any SIGSTOP here: a learner stopped past the lease is gone for the actor, which
        # then acts on to the run's end (on a loaded machine the lead cap's hold came after 3 s: no step was left)
        "--lease-ms", "10000"]
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
        s.put(key, encode(Correction(client="t", actor="a0", active=True, p_h=np.array([0.95, 0.95])), "t", seq))
        seq += 1
        if seq == 5:
            print("holding", flush=True)
        time.sleep(0.05)
"""


def _khgrl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*UP[:-1], *args], env=_env(), capture_output=True, text=True, timeout=60)


def _steps(log_path) -> int:
    from driver_log_task import read_log

    return sum(r[0] == "step" for r in read_log(log_path)) if log_path.exists() else 0


def _moving(log_path, n: int = 5, timeout: float = 30.0) -> None:
    """Wait until the driver gets ``n`` more steps."""
    start = _steps(log_path)
    wait_for(lambda: _steps(log_path) >= start + n, timeout, f"{n} more steps")


def _stalled(log_path, quiet: float = 1.0, timeout: float = 60.0) -> None:
    """Wait until the driver gets no step for ``quiet`` seconds (the actor has used its lead and holds)."""
    last, since, end = _steps(log_path), time.monotonic(), time.monotonic() + timeout
    while time.monotonic() - since < quiet:
        assert time.monotonic() < end, f"the actor never held in {timeout:g} s"
        time.sleep(0.1)
        if (n := _steps(log_path)) != last:
            last, since = n, time.monotonic()


def _estop(run_dir, seconds: float) -> tuple[float, float]:
    """Press the e-stop, hold ``seconds``, release; (when it was confirmed held, when the release began)."""
    press = _khgrl("stop", str(run_dir), "--now")
    assert press.returncode == 0 and "a0: held by the e-stop" in press.stdout, press.stdout + press.stderr
    held = time.time()
    time.sleep(seconds)
    released = time.time()
    release = _khgrl("stop", str(run_dir), "--release")
    assert release.returncode == 0 and "a0: released" in release.stdout, release.stdout + release.stderr
    return held, released


@pytest.fixture(scope="module")
def limits_run(tmp_path_factory):
    """The run of the module docstring: its driver log, its summary and what the test did when."""
    tmp = tmp_path_factory.mktemp("limits")
    shutil.copy(REPO / "tests" / "driver_log_task.py", tmp / "driver_log_task.py")
    log_path, push = tmp / "driver.log", tmp / "push"
    env = {**_env(), "KHGRL_DRIVER_LOG": str(log_path), "KHGRL_DRIVER_PUSH": str(push),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp), os.environ.get("PYTHONPATH", "")]))}
    up = Launcher(tmp, tmp / "run", *ARGS, env=env)
    events: dict = {}
    human = None
    try:
        pids = up.children(90)
        wait_for(lambda: _steps(log_path) > 20, 120, "the actor's first steps")
        events["readers"] = {cmd: _khgrl(*cmd.split(), str(up.run_dir)) for cmd in  # (eval: before the first
                             ("eval", f"export --lerobot {tmp / 'export'}", f"view --out {tmp / 'x.rrd'}")}  # model)
        events["overwrite"] = subprocess.run([*UP, "--run-dir", str(up.run_dir), "--overwrite", *ARGS], cwd=REPO,
                                             env=env, capture_output=True, text=True, timeout=120)
        events["ready"] = _khgrl("ready", str(up.run_dir))
        events["intact"] = up.proc.poll() is None and (up.run_dir / "config.json").is_file()
        os.kill(pids["human-scripted"], signal.SIGSTOP)  # 1. the actor waits for the lock-step word
        time.sleep(0.3)
        events["lockstep"] = _estop(up.run_dir, 1.0)
        time.sleep(TIMEOUT)  # the wait goes on after the release, and gives up on the client: plain mode from here
        os.kill(pids["human-scripted"], signal.SIGCONT)
        _moving(log_path)
        push.touch()  # 2. a hand on the arm while the e-stop holds it
        events["push"] = _estop(up.run_dir, 1.0)
        _moving(log_path)
        human = subprocess.Popen([sys.executable, "-c", HUMAN, *_endpoint(up.run_dir)], env=_env(),
                                 stdout=subprocess.PIPE, text=True, start_new_session=True)
        assert human.stdout.readline().strip() == "holding"  # 3. a live client drags, then dies mid-hold
        before = _steps(log_path)
        time.sleep(1.0)  # (and the actor stepping while it holds, on a loaded machine: killed between two steps)
        wait_for(lambda: _steps(log_path) >= before + 3, 60, "the actor's steps while the client holds")
        human.kill()
        human.wait(10)
        time.sleep(TIMEOUT)
        _moving(log_path)
        os.kill(pids["learner"], signal.SIGSTOP)  # 4. the wait for the learner: until the lead cap holds the actor
        _stalled(log_path)
        os.kill(pids["learner"], signal.SIGCONT)
        _moving(log_path)
        _stall(pids["a0"], up.run_dir / "actor-a0" / "actor.log")  # 5. a stalled control loop
        rc = up.proc.wait(timeout=300)  # 6. the path back to the start before episode 2
        assert rc == 0, f"khgrl up exited {rc}\n{up.stdout}\n{up.stderr}"
    finally:
        if human is not None and human.poll() is None:
            human.kill()
        up.cleanup()
    from driver_log_task import read_log

    summary = read_json(up.run_dir / "actor-a0" / "summary.json")
    return {"log": read_log(log_path), "summary": summary, "events": events, "run_dir": up.run_dir, "tmp": tmp}


def _stall(pid: int, actor_log: Path, tries: int = 8) -> None:
    """SIGSTOP the actor for 0.4 s until it logs a new step at least 300 ms late: a stop that falls on a wait (flow
    control, a hold) is not lateness, and on a loaded machine the actor may be waiting rather than stepping. (The
    actor logs late steps at most once per ``LATE_LOG_S``, 10 s: 8 tries span more.)"""
    start = len(actor_log.read_text())
    for _ in range(tries):
        try:
            os.kill(pid, signal.SIGSTOP)
        except ProcessLookupError:  # the run ended meanwhile (what the summary says is checked after)
            return
        time.sleep(0.4)
        os.kill(pid, signal.SIGCONT)
        time.sleep(1.0)
        late = [float(m) for m in re.findall(r"control step ([0-9.]+) ms late", actor_log.read_text()[start:])]
        if late and max(late) >= 300:
            return


def _endpoint(run_dir) -> tuple[str, str]:
    runtime = read_json(run_dir / "config.json")["runtime"]
    return runtime["endpoint"], runtime["run"]


def test_the_estop_holds_the_robot_while_the_actor_waits_for_a_lock_step_word(limits_run):
    """Defect 4. Before the fix: the e-stop came while the actor waited for the SIGSTOPped client's word; it went on
    waiting for the full 3 s correction timeout, gave up, took the step and only then held (the delay from the
    command to the hold ~2.5 s; the step at which it was pressed was sent before the release)."""
    s, log = limits_run["summary"]["safety"], limits_run["log"]
    first = s["estop_events"][0]
    print(f"e-stop while waiting for a lock-step word: held {first['latency_ms']:.1f} ms after the command "
          f"(period {1e3 / RATE:.0f} ms)")
    assert first["latency_ms"] <= 250.0, s["estop_events"]  # held at once, not after the wait
    held, released = limits_run["events"]["lockstep"]
    (sent,) = [r[1] for r in log if r[0] == "step" and r[2] == first["episode"] and r[3] == first["t"]]
    assert sent > released, (sent, held, released)  # the step the e-stop caught was taken after the release
    caught = [r for r in log if r[0] == "step" and r[2] == first["episode"] and held - 2.0 <= r[1] <= released]
    assert all(r[3] < first["t"] for r in caught), caught


def test_a_live_run_is_not_overwritten_and_ready_says_nothing_waited(limits_run):
    """Defect 8. Before the fix ``khgrl up --overwrite`` deleted the live run's files and started a second run on
    them, and ``khgrl ready`` printed "ready confirmed" with nothing waiting for it."""
    again, ready = limits_run["events"]["overwrite"], limits_run["events"]["ready"]
    assert again.returncode == 2, again.stdout + again.stderr
    assert "is still running" in again.stderr and "launcher (pid" in again.stderr, again.stderr
    assert len(again.stderr.strip().splitlines()) == 1, again.stderr
    assert limits_run["events"]["intact"]  # the run went on, its files in place (it then ended with exit 0)
    assert ready.returncode == 1 and "nothing was waiting for ready" in ready.stderr, ready.stdout + ready.stderr
    assert "a0: not waiting for ready" in ready.stdout and "confirmed" not in ready.stdout, ready.stdout


def test_the_tools_for_a_finished_run_refuse_a_live_one(limits_run):
    """Issue 36's friction: ``khgrl export`` and ``khgrl view`` of a run still running succeeded silently with the
    half-written files, and ``khgrl eval`` blamed a missing checkpoint. Each is one line naming the live run, exit 2
    (eval: the run has no checkpoint yet when it is asked), and nothing is written."""
    for cmd, done in limits_run["events"]["readers"].items():
        assert done.returncode == 2, (cmd, done.stdout, done.stderr)
        assert "is still running" in done.stderr and "launcher (pid" in done.stderr, (cmd, done.stderr)
        assert len(done.stderr.strip().splitlines()) == 1, (cmd, done.stderr)
    assert not (limits_run["tmp"] / "export").exists() and not (limits_run["tmp"] / "x.rrd").exists()


def test_every_command_the_driver_gets_is_within_both_limits_after_every_kind_of_hold(limits_run):
    """Defect 5. Before the fix the velocity went on through every hold (the first step after the e-stop's release,
    the silent human's freeze, the wait for the learner and the stalled loop from standstill: up to 2 d, the
    acceleration limit is 0.5 d), the path back to the start began "from rest" while the robot moved (a change of
    step of 1.5-2.5 d), and after the hand moved the arm the commands restarted from the position last sent, 6 d
    from where the robot was."""
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.delta import largest_step
    from khgrl.common.tasks.world import build_task_world

    log, s = limits_run["log"], limits_run["summary"]["safety"]
    d = largest_step(build_task_world(load_task("passage:low_cov")).demos)
    speed, accel, tol = 2.0 * d, 0.5 * d, 1e-9
    assert s["estops"] == 2 and s["human_silence_holds"] >= 1 and s["learner_holds"] >= 1, s
    assert s["late_steps"] >= 1 and s["late_ms_max"] >= 300, s
    assert len(s["reset_paths"]) == 2 and all(r["steps"] > 0 for r in s["reset_paths"]), s  # (3 episodes)
    assert any(r[0] == "push" for r in log), "the hand moved the arm while it was held"
    ref, v, worst, checked, after_hold = None, np.zeros(2), (0.0, 0.0), 0, 0
    for i, r in enumerate(log):
        if r[0] in ("reset", "hold"):
            ref, v = np.array(r[-2:]), np.zeros(2)  # where the robot is, at rest
            continue
        if r[0] != "step":
            continue
        p = np.array(r[4:6])
        u = p - ref
        worst = (max(worst[0], float(np.max(np.abs(u))) / d), max(worst[1], float(np.max(np.abs(u - v))) / d))
        assert np.max(np.abs(u)) <= speed + tol and np.max(np.abs(u - v)) <= accel + tol, (r, ref, v, u, log[i - 8:i])
        after_hold += int(not np.any(v))
        ref, v, checked = p, u, checked + 1
    print(f"{checked} commands checked ({after_hold} from rest); largest step {worst[0]:.3f} d, largest change of "
          f"step {worst[1]:.3f} d (limits 2 d and 0.5 d)")
    assert checked > 200 and after_hold >= 5
