"""``khgrl up`` as a new user meets it: the launcher defects of issue 10, each against the real processes
(``python -m khgrl.deploy.cli up ...``: router, learner, actor, human-input client).

* an unreachable ``--connect`` router: a clear error naming it within ``--connect-timeout``;
* SIGTERM stops the launcher and every child within seconds, in every state (waiting for a router, while the
  children start, while they run);
* children never outlive a SIGKILLed launcher (parent-death signal);
* a run directory holding a run is refused unless ``--resume`` or ``--overwrite``;
* ``--resume`` continues the run (episode numbers, episodes.csv, corrections.csv, the learner's checkpoint, the
  scripted human's schedule in whole-run episodes), and is an error on the console when there is nothing to resume;
* ``--human gui`` without a display fails the run loudly;
* a stop command from elsewhere ends the run with a non-zero exit.

The children's process ids come from ``RUN_DIR/pids.json`` (written by the launcher); whatever is left at the
end of a test is killed by PID.
"""

from __future__ import annotations

import shutil
import signal
import time
from pathlib import Path

import pytest

from helpers import FULL_UTD, pid_alive, read_json, untimed, wait_for
from launch import FAST, HUMAN_EPISODE, KGRL, Launcher, _env, _ingested, _rows, _run

pytestmark = pytest.mark.integration

def _alive(pids) -> list[int]:
    return [p for p in pids if pid_alive(p)]


# ===================================================================================== 1. unreachable router
@pytest.mark.timeout(120)
def test_unreachable_router_is_a_clear_error_within_the_connect_timeout(tmp_path):
    """With ``--connect-timeout 3``; the default (15 s) is the same path, and test_config checks its value."""
    run_dir = tmp_path / "run"
    t0 = time.monotonic()
    expect = 3
    proc = _run(run_dir, *KGRL, "--episodes", "1", "--connect", "tcp/127.0.0.1:1", "--connect-timeout", str(expect),
                timeout=60)
    took = time.monotonic() - t0
    assert proc.returncode == 1, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert f"no Zenoh router reachable at tcp/127.0.0.1:1 within {expect} s" in proc.stderr, proc.stderr
    assert took < expect + 15, f"took {took:.0f} s with a connect timeout of {expect} s"
    assert not run_dir.exists() or not any(run_dir.iterdir()), "a run that never started left files"


# ============================================================================================ 2. SIGTERM
@pytest.mark.timeout(120)
def test_sigterm_while_waiting_for_an_unreachable_router(tmp_path):
    up = Launcher(tmp_path, tmp_path / "run", *KGRL, "--episodes", "1", "--connect", "tcp/127.0.0.1:1")
    try:
        time.sleep(6.0)  # interpreter start, imports, then the wait for the router (15 s by default)
        assert up.proc.poll() is None, f"khgrl up exited {up.proc.returncode}\n{up.stderr}"
        t0 = time.monotonic()
        up.proc.send_signal(signal.SIGTERM)
        rc = up.proc.wait(timeout=30)
        took = time.monotonic() - t0
        assert rc == 128 + signal.SIGTERM, f"exit code {rc}\n{up.stderr}"
        assert took < 10, f"took {took:.0f} s to stop on SIGTERM"
        assert "tcp/127.0.0.1:1" in up.stderr
    finally:
        up.cleanup()


@pytest.mark.timeout(300)
@pytest.mark.parametrize("state", ["starting", "running"])
def test_sigterm_stops_khgrl_up_and_every_child(tmp_path, state):
    """While the children start (they have not subscribed to the stop command yet) and while they run."""
    up = Launcher(tmp_path, tmp_path / "run", *FAST, "--episodes", "1000", "--human-episodes", "2",
                  "--max-lead", "100000", "--rate", "100")
    try:
        children = up.children()
        assert len(children) == 4, f"expected router, learner, a0, human-scripted: {children}"
        if state == "running":
            up.wait_line("[a0] episode 1:", 180)
        t0 = time.monotonic()
        up.proc.send_signal(signal.SIGTERM)
        rc = up.proc.wait(timeout=60)
        took = time.monotonic() - t0
        assert rc == 128 + signal.SIGTERM, f"exit code {rc}\n{up.stdout}\n{up.stderr}"
        assert took < 15, f"took {took:.0f} s to stop on SIGTERM ({state})"
        assert not _alive(children.values()), f"children alive after khgrl up exited: {children}"
        summary = read_json(up.run_dir / "summary.json")
        assert summary["interrupted"] is True and all(c is not None for c in summary["exit_codes"].values())
    finally:
        up.cleanup()


# ================================================================================= 3. SIGKILL of the launcher
@pytest.mark.timeout(300)
def test_children_die_with_a_killed_launcher(tmp_path):
    up = Launcher(tmp_path, tmp_path / "run", *FAST, "--episodes", "1000", "--human-episodes", "2",
                  "--max-lead", "100000", "--rate", "100")
    try:
        children = up.children()
        up.wait_line("[a0] episode 1:", 180)
        assert not set(children.values()) - set(_alive(children.values())), "a child died early"
        up.proc.kill()
        up.proc.wait(10)
        try:
            wait_for(lambda: not _alive(children.values()), 20, "every child to exit after the launcher's SIGKILL")
        except AssertionError:
            raise AssertionError(f"orphans still running 20 s after the launcher was killed: "
                                 f"{ {n: p for n, p in children.items() if pid_alive(p)} }") from None
    finally:
        up.cleanup()


# ================================================================== 4./5. an existing run: refused, resumed, redone
@pytest.fixture(scope="module")
def first_part(tmp_path_factory):
    """Two episodes of a KhGRL run whose scripted human helps in episode 3 (so not yet)."""
    run_dir = tmp_path_factory.mktemp("first") / "run"
    proc = _run(run_dir, *FAST, *FULL_UTD, "--episodes", "2", "--human-episodes", str(HUMAN_EPISODE))
    assert proc.returncode == 0, f"khgrl up exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return run_dir


def _copy(run_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(run_dir, dst, symlinks=True)
    return dst


@pytest.mark.timeout(300)
def test_a_run_directory_with_a_run_is_refused(first_part):
    episodes = first_part / "actor-a0" / "episodes.csv"
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in (episodes, first_part / "config.json",
                                                                  first_part / "summary.json")}
    proc = _run(first_part, *FAST, "--episodes", "2", timeout=60)
    assert proc.returncode == 2, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert f"run directory {first_part} already holds a run" in proc.stderr, proc.stderr
    assert "--resume" in proc.stderr and "--overwrite" in proc.stderr
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in before} == before, "the earlier run was touched"


@pytest.mark.timeout(300)
def test_overwrite_deletes_the_earlier_run_first(first_part, tmp_path):
    run_dir = _copy(first_part, tmp_path)
    proc = _run(run_dir, *FAST, "--episodes", "1", "--human-episodes", str(HUMAN_EPISODE), "--overwrite")
    assert proc.returncode == 0, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert f"khgrl up: --overwrite: deleted the earlier run in {run_dir}" in proc.stdout, proc.stdout
    rows = _rows(run_dir)
    assert [int(r["episode"]) for r in rows] == [1]
    assert _ingested(run_dir) == int(rows[0]["steps"]), "the earlier run's transitions are in the new checkpoint"
    assert read_json(run_dir / "config.json")["runtime"]["resumed"] is False
    assert not list(run_dir.glob("config-part*"))
    first_log = (first_part / "logs" / "a0.log").read_text()
    assert first_log[:200] not in (run_dir / "logs" / "a0.log").read_text(), "the earlier run's log was kept"


@pytest.mark.timeout(300)
def test_the_run_config_reproduces_the_run(first_part, tmp_path):
    """``khgrl up --config RUN_DIR/config.toml`` runs the same configuration again: the same resolved settings
    (but the run directory) and, seeded, the same episodes (every column but wall time)."""
    again = tmp_path / "again"
    proc = _run(again, "--config", str(first_part / "config.toml"), "--no-progress")
    assert proc.returncode == 0, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    first, second = (read_json(d / "config.json") for d in (first_part, again))
    for cfg in (first, second):
        cfg.pop("runtime")
        cfg.pop("run_dir")
    assert first == second
    assert untimed(_rows(again)) == untimed(_rows(first_part))


@pytest.mark.timeout(400)
def test_resume_continues_episodes_corrections_checkpoint_and_the_human_schedule(first_part, tmp_path):
    run_dir = _copy(first_part, tmp_path)
    part1 = (run_dir / "actor-a0" / "episodes.csv").read_text().splitlines()
    config1 = read_json(run_dir / "config.json")
    # no --config: RUN_DIR/config.toml is the base; --episodes 3 continues the run to 3 episodes
    proc = _run(run_dir, "--resume", "--episodes", "3", "--no-progress")
    assert proc.returncode == 0, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    lines = [ln.split(":")[0] for ln in proc.stdout.splitlines() if ln.startswith("[a0] episode")]
    assert lines == ["[a0] episode 3"], proc.stdout
    rows = _rows(run_dir)
    assert [int(r["episode"]) for r in rows] == [1, 2, 3], "episode numbering did not continue"
    assert (run_dir / "actor-a0" / "episodes.csv").read_text().splitlines()[:3] == part1, \
        "the first part's episodes were rewritten"
    # the scripted human's schedule counts episodes of the whole run: it helps in episode 3 only
    assert [int(r["intervention_steps"]) > 0 for r in rows] == [False, False, True], rows
    corrections = _rows(run_dir, "corrections.csv")
    assert corrections and {int(r["episode"]) for r in corrections} == {HUMAN_EPISODE}
    # the learner continued from its checkpoint: every transition of the run in the buffer once
    assert _ingested(run_dir) == sum(int(r["steps"]) for r in rows)
    # the configuration of both parts is kept
    runtime = read_json(run_dir / "config.json")["runtime"]
    assert runtime["resumed"] is True and runtime["part"] == 2 and runtime["run"] == config1["runtime"]["run"]
    assert runtime["first_started"] == config1["runtime"]["started"]
    assert read_json(run_dir / "config-part1.json") == config1
    assert read_json(run_dir / "config.json")["episodes"] == 3 and config1["episodes"] == 2
    assert read_json(run_dir / "summary.json")["resumed"] is True and (run_dir / "summary-part1.json").exists()


@pytest.mark.timeout(120)
def test_resume_with_nothing_to_resume_is_an_error(tmp_path):
    from khgrl.common.config.settings import RunConfig, write_run_config

    empty = tmp_path / "empty"
    proc = _run(empty, *KGRL, "--resume", timeout=60)
    assert proc.returncode == 2, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert f"--resume: nothing to resume in {empty}: it has no config.toml" in proc.stderr, proc.stderr
    started = tmp_path / "started"  # configured, but no learner checkpoint yet
    write_run_config(started, RunConfig(run_dir=str(started)), {"run": "x"})
    proc = _run(started, "--resume", "--no-progress", timeout=60)
    assert proc.returncode == 2, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "no learner checkpoint" in proc.stderr, proc.stderr
    assert not (started / "logs").exists(), "a process was started"


# ============================================================================================ 6. no display
@pytest.mark.timeout(300)
def test_gui_without_a_display_fails_the_run_loudly(tmp_path):
    run_dir = tmp_path / "run"
    t0 = time.monotonic()
    proc = _run(run_dir, *FAST, "--episodes", "2", "--human", "gui", env=_env(no_display=True), timeout=200)
    took = time.monotonic() - t0
    assert proc.returncode == 1, f"exit code {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "khgrl up: process human-gui exited with code" in proc.stderr, proc.stderr
    assert "last lines of" in proc.stderr
    summary = read_json(run_dir / "summary.json")
    assert summary["failed"] == ["human-gui"] and summary["exit_codes"]["human-gui"] not in (0, None), summary
    assert took < 120, f"took {took:.0f} s to fail"


# ================================================================================= 7. a stop from elsewhere
@pytest.mark.timeout(300)
def test_a_stop_command_from_elsewhere_is_a_failure(tmp_path):
    from khgrl.common.delivery.control_auth import OPERATOR, ControlSigner
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Control
    from khgrl.common.wire.protocol import Keys, encode

    up = Launcher(tmp_path, tmp_path / "run", *KGRL, "--episodes", "1000", "--max-lead", "100000",
                  "--rate", "100")
    try:
        up.wait_line("[a0] episode 1:", 180)
        runtime = read_json(up.run_dir / "config.json")["runtime"]
        with open_client(runtime["endpoint"], timeout=30) as session:
            key = Keys(runtime["run"]).control("all")
            session.put(key, encode(Control(command="stop"), "mallory", 0))  # unsigned: refused, the run goes on
            # the operator's at another terminal (signed with its key, as khgrl stop does): the launcher knows its
            # own session's commands, not the name
            session.put(key, ControlSigner.load(up.run_dir, OPERATOR).payload(key, "stop", "launcher", 0))
            rc = up.proc.wait(timeout=90)
        assert rc == 1, f"exit code {rc}\n{up.stdout}\n{up.stderr}"
        assert "stopped by a stop command from 'launcher'" in up.stderr, up.stderr
        assert "from another session" in up.stderr, up.stderr
        assert read_json(up.run_dir / "summary.json")["stopped_by"].startswith("a stop command from 'launcher'")
    finally:
        up.cleanup()
