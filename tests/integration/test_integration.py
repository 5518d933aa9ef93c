"""Integration tests: the real KhGRL processes (router, learner, actor, scripted human, ``khgrl up``) over a real
Zenoh router, started as a user starts them.

Every run gets an explicit free port (``khgrl up --port``), a unique run id (``--run``), multicast scouting off
(the processes' session config), hard timeouts, and whatever is left at the end is killed by PID (the launcher's
Popen handle, and its children from ``RUN_DIR/pids.json``).

Costs on a 2-core box: one ``khgrl up`` of 3 low_cov episodes is ~55 s (process start-up, then the actor in
lock-step with the learner after ``--learning-starts 64``); it is shared by the end-to-end and the correction tests
(module fixture). The launcher's own defects (unreachable router, signals, orphans, run directories, resume,
no display) are tested in test_launcher.py.
"""

from __future__ import annotations

import ast
import csv
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from helpers import (
    FULL_UTD,
    REPO,
    SMALL,
    free_port,
    kill_pids,
    pid_alive,
    read_json,
    unique_run,
    wait_for,
)

UP = [sys.executable, "-m", "khgrl.deploy.cli", "up"]
FAST = ["--scenario", "low_cov", "--method", "khgrl", "--learning-starts", "64", *SMALL]
HUMAN_EPISODE = 2  # the scripted human helps in this episode only


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RUST_LOG", "error")
    return env


def _up_argv(run_dir: Path, port: int, run: str, *args: str) -> list[str]:
    return [*UP, *args, "--run-dir", str(run_dir), "--port", str(port), "--run", run]


def _children(run_dir: Path) -> list[int]:
    """The PIDs of the launcher's children (``RUN_DIR/pids.json``) still alive."""
    path = run_dir / "pids.json"
    return [p for p in read_json(path)["children"].values() if pid_alive(p)] if path.exists() else []


def _cleanup(launcher: subprocess.Popen | None, run_dir: Path) -> None:
    """Kill the launcher (if still there) and its children, by PID."""
    if launcher is not None and launcher.poll() is None:
        launcher.kill()
        launcher.wait(10)
    kill_pids(_children(run_dir))


def _episodes_csv(run_dir: Path, actor: str = "a0") -> list[dict]:
    with open(run_dir / f"actor-{actor}" / "episodes.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _checkpoint(run_dir: Path) -> tuple[dict, dict[str, np.ndarray]]:
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    ck = run_dir / "learner" / "checkpoint"
    return read_json(ck / "state.json"), load_checkpoint_arrays(ck)


def _filled(state: dict) -> int:
    return state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]


def _actor_slots(state: dict, arrays: dict, actor: str) -> np.ndarray:
    """Replay-buffer slots that hold ``actor``'s transitions (any of its streams)."""
    n = _filled(state)
    codes = [c for c, e in enumerate(state["codes"]) if e["actor"] == actor]
    return np.flatnonzero(np.isin(arrays["provenance_actor"][:n], codes))


def _assert_exactly_once(state: dict, arrays: dict, actor: str, n: int) -> np.ndarray:
    """Every step 0..n-1 of ``actor`` is in the buffer exactly once, nothing else; returns slots sorted by step."""
    fill = _filled(state)
    assert np.all(arrays["provenance_actor"][:fill] >= 0), "an empty slot inside the filled part of the buffer"
    assert [e["actor"] for e in state["codes"]] == [actor], f"unexpected streams in the buffer: {state['codes']}"
    slots = _actor_slots(state, arrays, actor)
    steps = arrays["provenance_step"][slots]
    order = np.argsort(steps, kind="stable")
    assert steps[order].tolist() == list(range(n)), f"{actor}: provenance is not its steps 0..{n - 1} exactly once"
    return slots[order]


def _episode_of(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(episode number, step t in the episode) for each of the actor's running indices."""
    ep, t = [], []
    for r in rows:
        k = int(r["steps"])
        ep += [int(r["episode"])] * k
        t += list(range(k))
    return np.array(ep), np.array(t)


# =========================================================================================== khgrl up, 3 episodes
@pytest.fixture(scope="module")
def up_run(tmp_path_factory):
    """``khgrl up`` as a user runs it: low_cov, khgrl, 3 episodes, the scripted human in episode 2."""
    base = tmp_path_factory.mktemp("up")
    run_dir, port, run = base / "run", free_port(), unique_run("up")
    endpoint = f"tcp/127.0.0.1:{port}"
    argv = _up_argv(run_dir, port, run, *FAST, "--episodes", "3", "--human-episodes", str(HUMAN_EPISODE),
                    "--no-progress")
    t0 = time.monotonic()
    leftover = None
    try:
        proc = subprocess.run(argv, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=200)
        leftover = _children(run_dir)
    finally:
        _cleanup(None, run_dir)  # children of a launcher killed by the timeout
    return {"proc": proc, "run_dir": run_dir, "run": run, "endpoint": endpoint, "wall": time.monotonic() - t0,
            "leftover": leftover}


@pytest.mark.integration
@pytest.mark.timeout(260)
def test_up_runs_to_completion_and_writes_the_run_dir(up_run):
    proc, run_dir = up_run["proc"], up_run["run_dir"]
    assert proc.returncode == 0, f"khgrl up exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert f"khgrl up: run {up_run['run']} on {up_run['endpoint']}" in proc.stdout
    assert up_run["leftover"] == [], "processes of the run still alive after khgrl up exited"
    config = read_json(run_dir / "config.json")
    assert config["runtime"]["run"] == up_run["run"] and config["runtime"]["endpoint"] == up_run["endpoint"]
    assert config["episodes"] == 3 and config["human_episodes"] == [HUMAN_EPISODE]  # the resolved settings
    summary = read_json(run_dir / "summary.json")
    assert summary["exit_codes"] == {"router": 0, "learner": 0, "a0": 0, "human-scripted": 0}, summary
    assert summary["failed"] == [] and summary["interrupted"] is False
    for name in ("router", "learner", "a0", "human-scripted"):
        log = run_dir / "logs" / f"{name}.log"
        assert log.exists() and log.stat().st_size > 0, f"no log for {name}"
    rows = _episodes_csv(run_dir)
    assert [int(r["episode"]) for r in rows] == [1, 2, 3]
    by_ep = {int(r["episode"]): r for r in rows}
    assert int(by_ep[HUMAN_EPISODE]["intervention_steps"]) > 0, rows
    assert all(int(by_ep[e]["intervention_steps"]) == 0 for e in (1, 3)), "corrections outside the human's episode"
    # the launcher printed one line per episode, in order
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("[a0] episode")]
    assert [ln.split(":")[0] for ln in lines] == [f"[a0] episode {e}" for e in (1, 2, 3)], proc.stdout
    actor = read_json(run_dir / "actor-a0" / "summary.json")
    assert actor["exit_code"] == 0 and actor["episodes"] == 3 and actor["unconfirmed_transitions"] == 0
    assert actor["rejects"] == {}, "a clean run rejected messages"
    assert summary["a0"]["transitions"] == actor["transitions"] == sum(int(r["steps"]) for r in rows)


@pytest.mark.integration
@pytest.mark.timeout(260)
def test_up_checkpoint_holds_each_step_once_with_exactly_the_intervened_flags(up_run):
    assert up_run["proc"].returncode == 0, up_run["proc"].stderr
    run_dir = up_run["run_dir"]
    rows = _episodes_csv(run_dir)
    n = sum(int(r["steps"]) for r in rows)
    state, arrays = _checkpoint(run_dir)
    assert state["total_ingested"] == n
    slots = _assert_exactly_once(state, arrays, "a0", n)  # slots[i] holds the actor's step i
    iv = arrays["intervened"][slots].astype(bool)
    cl = arrays["clipped"][slots].astype(bool)
    ep, _ = _episode_of(rows)
    assert int(iv.sum()) == sum(int(r["intervention_steps"]) for r in rows)
    assert int(cl.sum()) == sum(int(r["clipped_steps"]) for r in rows)
    assert not np.any(cl & ~iv), "a clipped flag on a step without intervention"
    for r in rows:
        e = int(r["episode"])
        m = iv[ep == e]
        assert int(m.sum()) == int(r["intervention_steps"]), f"episode {e}: intervened flags vs episodes.csv"
        assert int(cl[ep == e].sum()) == int(r["clipped_steps"]), f"episode {e}: clipped flags vs episodes.csv"
        segments = int(np.sum(m[1:] & ~m[:-1]) + (m[0] if m.size else 0))
        assert segments == int(r["interventions"]), f"episode {e}: {segments} flagged segments vs episodes.csv"


# ================================================================== the scripted human's corrections, as stored
@pytest.fixture(scope="module")
def low_cov_env():
    from khgrl.common.tasks.passage.env import PassageEnv

    return PassageEnv("low_cov")  # the actor's world (same seeds); fitting takes a few seconds


@pytest.mark.integration
@pytest.mark.timeout(260)
def test_intervened_transitions_store_the_scripted_humans_actions(up_run, low_cov_env):
    """The scripted human sends step-addressed corrections and the actor waits for them (lock-step), so the run
    intervenes at exactly the steps where the scripted human, asked at that step's KMP mean, gives a P_h -- as the
    single-process reference does -- and stores clip(xi_h / L) for exactly that P_h, computed here, independently
    of the actor's process."""
    from khgrl.common.tasks.passage.task import segment_blocked as _segment_blocked
    from khgrl.human_bridge.scripted import ScriptedHuman, ScriptedHumanConfig
    from stable_baselines3.common.save_util import load_from_pkl

    assert up_run["proc"].returncode == 0, up_run["proc"].stderr
    run_dir = up_run["run_dir"]
    env = low_cov_env
    mapping, model = env.mapping, env.world.model
    rows = _episodes_csv(run_dir)
    n = sum(int(r["steps"]) for r in rows)
    state, arrays = _checkpoint(run_dir)
    slots = _assert_exactly_once(state, arrays, "a0", n)
    rb = load_from_pkl(run_dir / "learner" / "checkpoint" / "replay_buffer.pkl")
    obs, nobs, act = rb.observations[slots, 0], rb.next_observations[slots, 0], rb.actions[slots, 0]
    iv = arrays["intervened"][slots].astype(bool)
    cl = arrays["clipped"][slots].astype(bool)
    ep, t = _episode_of(rows)
    # provenance and stored observations agree: the phase in obs is the step's phase
    np.testing.assert_allclose(obs[:, 2], mapping.phases[t], atol=1e-6)

    assert np.all(np.abs(act) <= 1.0), "a stored action outside [-1, 1]"
    # the clipped flag is set exactly where the stored human action sits on the box
    assert np.all(np.max(np.abs(act[cl]), axis=1) == 1.0)
    if np.any(iv & ~cl):
        assert np.all(np.max(np.abs(act[iv & ~cl]), axis=1) < 1.0)

    # lock-step: intervened exactly where the scripted human, asked at step t's mean, has a P_h (as in one process)
    human = ScriptedHuman("low_cov", ScriptedHumanConfig(episodes=(HUMAN_EPISODE,)))
    in_ep = np.flatnonzero(ep == HUMAN_EPISODE)
    wanted = np.array([human.correction(HUMAN_EPISODE, mapping.mean(int(t[i]))) is not None for i in in_ep])
    assert wanted.any(), "the human episode never reached the help window"
    np.testing.assert_array_equal(iv[in_ep], wanted, err_msg="intervened steps vs the scripted human's window")
    ep_iv = in_ep[wanted]
    # low_cov: the demonstrations agree around the second wall, so the human's xi_h maps far outside the box
    assert np.mean(np.abs(act[ep_iv, 1]) == 1.0) >= 0.5, act[ep_iv]
    # the actor's record of what it applied: the scripted human's P_h for that very step
    rec = [r for r in csv.DictReader(open(run_dir / "actor-a0" / "corrections.csv"))]
    assert [(int(r["episode"]), int(r["step"])) for r in rec] == [(HUMAN_EPISODE, int(t[i])) for i in ep_iv]
    for r in rec:
        expect = human.correction(HUMAN_EPISODE, mapping.mean(int(r["step"])))
        assert (float(r["p_h_x"]), float(r["p_h_y"])) == (float(expect[0]), float(expect[1])), r

    # the first intervention segment runs with the initial exploration scale (the actor refits L when it ends)
    first = [ep_iv[0]]
    while first[-1] + 1 < n and iv[first[-1] + 1]:
        first.append(first[-1] + 1)
    assert len(first) >= 10, f"intervention segment of only {len(first)} steps"
    L = np.full(2, env.scenario.default_scale)
    xi_sum = 0.0
    for i in first:
        ti = int(t[i])
        p, q = obs[i, :2].astype(np.float64), nobs[i, :2].astype(np.float64)
        p_h = human.correction(HUMAN_EPISODE, mapping.mean(ti))
        d = p_h - p
        dist = float(np.hypot(*d))
        target = p + (d if dist <= env.speed else d * (env.speed / dist))
        pred, _ = _segment_blocked(p, target, env.scenario.walls)
        np.testing.assert_allclose(q, pred, atol=2e-6, err_msg=f"t={ti}: the robot did not move toward this step's P_h")
        xi = model.grid_invert_constrained(ti, p_h)
        np.testing.assert_allclose(act[i], np.clip(xi / L, -1.0, 1.0).astype(np.float32), atol=1e-6,
                                   err_msg=f"t={ti}: stored action vs clip(xi_h / L) for this step's P_h")
        assert bool(cl[i]) == bool(np.any(np.abs(xi / L) > 1.0)), f"t={ti}: clipped flag"
        xi_sum += float(np.mean(np.abs(xi)))
    # the actor's own per-episode mean |xi_h| agrees with the xi_h computed here (single segment only)
    row = next(r for r in rows if int(r["episode"]) == HUMAN_EPISODE)
    if int(row["interventions"]) == 1:
        assert len(first) == int(row["intervention_steps"])
        np.testing.assert_allclose(float(row["mean_abs_xi_h"]), xi_sum / len(first), rtol=1e-6)
    actor = read_json(run_dir / "actor-a0" / "summary.json")
    assert actor["corrections"]["lockstep_timeouts"] == 0, actor["corrections"]


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_env_correction_stores_clipped_inverse_of_the_scripted_p_h(low_cov_env):
    """In process, no Zenoh: PassageEnv.set_correction(P_h) with the scripted human's P_h moves the desired
    position to P_h and stores clip(xi_h / L) with xi_h the constrained inverse (eq. 6) -- checked against the
    forward LC-NS-KMP map (grid_step(t, xi_h) == P_h) and, with a large L, unclipped (a_h * L == xi_h)."""
    from khgrl.common.kmp.scale import ScaleModel
    from khgrl.common.tasks.passage.env import PassageEnv
    from khgrl.human_bridge.scripted import ScriptedHuman, ScriptedHumanConfig

    human = ScriptedHuman("low_cov", ScriptedHumanConfig(episodes=(1,)))
    rng = np.random.default_rng(0)
    envs = {"L0": low_cov_env, "large": PassageEnv("low_cov", scale_model=ScaleModel(1e6, dim=2))}
    for name, env in envs.items():
        model, mapping = env.world.model, env.mapping
        env.reset(seed=0)
        checked = clipped = 0
        done = False
        while not done and checked < 25:
            t = env.t
            p_h = human.correction(1, mapping.mean(t - 1)) if t > 0 else None  # the frame of the previous step
            env.set_correction(p_h)
            robot = env.robot.copy()
            L = mapping.scale_at(t, robot)
            # on the mean until the human takes over (reaches the window); then the policy's action is ignored
            policy = np.zeros(2, np.float32) if p_h is None else rng.uniform(-1, 1, 2).astype(np.float32)
            _, _, te, tr, info = env.step(policy)
            done = te or tr
            if p_h is None:
                assert not info["intervened"] and np.array_equal(info["action"], policy)
                continue
            assert info["intervened"] and not info["projected"]
            np.testing.assert_array_equal(info["desired"], p_h)
            xi = model.grid_invert_constrained(t, p_h)
            np.testing.assert_allclose(info["xi_h"], xi, rtol=1e-9, atol=1e-9)
            # independent of the inverse: the forward map (the KGRL path) with xi_h reaches P_h
            np.testing.assert_allclose(model.grid_step(t, np.asarray(info["xi_h"])), p_h, atol=1e-7)
            expect = np.clip(xi / L, -1.0, 1.0)
            np.testing.assert_allclose(info["action"], expect.astype(np.float32), rtol=1e-6, atol=1e-7)
            assert info["action"].dtype == np.float32
            assert info["clipped"] == bool(np.any(np.abs(xi / L) > 1.0))
            if not info["clipped"]:  # the stored action reproduces xi_h, hence P_h
                np.testing.assert_allclose(info["action"].astype(np.float64) * L, xi, rtol=1e-6)
            # the robot heads for P_h at the speed limit (no wall in the way in the human's window here)
            step = env.robot - robot
            assert np.hypot(*step) <= env.speed + 1e-12
            np.testing.assert_allclose(step / np.hypot(*step), (p_h - robot) / np.hypot(*(p_h - robot)), atol=1e-6)
            checked += 1
            clipped += int(info["clipped"])
        assert checked >= 10, f"{name}: only {checked} corrected steps"
        if name == "L0":
            assert clipped >= checked // 2, "low_cov with the initial L: the human's actions should mostly clip"
        else:
            assert clipped == 0, "with L = 1e6 nothing should clip"
    assert envs["large"].world is low_cov_env.world  # one (cached) world: the same P_h gives the same xi_h


# ============================================================================================== Ctrl-C
@pytest.mark.integration
@pytest.mark.timeout(200)
def test_ctrl_c_stops_khgrl_up_and_every_child(tmp_path):
    run_dir, port, run = tmp_path / "run", free_port(), unique_run("int")
    argv = _up_argv(run_dir, port, run, *FAST, "--episodes", "1000", "--human-episodes", "2", "--max-lead", "100000",
                    "--rate", "100", "--no-progress")
    err_path = tmp_path / "up.stderr"
    lines: queue.Queue = queue.Queue()
    seen: list[str] = []
    launcher = None
    try:
        with open(err_path, "w") as err:
            launcher = subprocess.Popen(argv, cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=err, text=True,
                                        start_new_session=True)

            def reader():
                for ln in launcher.stdout:
                    lines.put(ln)

            threading.Thread(target=reader, daemon=True).start()
            deadline = time.monotonic() + 120
            while not any(s.startswith("[a0] episode 1:") for s in seen):
                assert time.monotonic() < deadline, f"no first episode line within 120 s:\n{''.join(seen)}"
                assert launcher.poll() is None, f"khgrl up exited {launcher.returncode}:\n{''.join(seen)}"
                try:
                    seen.append(lines.get(timeout=0.5))
                except queue.Empty:
                    pass
            children = _children(run_dir)
            assert len(children) == 4, f"expected router, learner, a0, human: {children}"
            # Ctrl-C in a terminal: SIGINT to the foreground process group (the launcher's; children have their own)
            t0 = time.monotonic()
            os.killpg(launcher.pid, signal.SIGINT)
            rc = launcher.wait(timeout=90)
            took = time.monotonic() - t0
        out = "".join(seen) + "".join(lines.get_nowait() for _ in range(lines.qsize()))
        assert rc == 130, f"exit code {rc}\n{out}\n{err_path.read_text()}"
        assert took < 20, f"took {took:.0f} s to stop"
        alive = [p for p in children if pid_alive(p)]
        assert not alive, f"children still alive after Ctrl-C: {alive}"
        summary = read_json(run_dir / "summary.json")
        assert summary["interrupted"] is True
        assert all(c is not None for c in summary["exit_codes"].values()), summary
        actor = read_json(run_dir / "actor-a0" / "summary.json")
        assert actor["stopped_by"] == "stop command" and 1 <= actor["episodes"] < 1000
        # the learner stopped on the launcher's stop and wrote a final checkpoint
        assert "stopping (stop command): final checkpoint" in (run_dir / "logs" / "learner.log").read_text()
        assert (run_dir / "learner" / "checkpoint" / "state.json").exists()
    finally:
        _cleanup(launcher, run_dir)


# ================================================================================= hostile messages on every topic
def _env_msg(kind: str, sender: str = "evil", seq: int = 0, **fields) -> dict:
    return {"v": 1, "kind": kind, "sender": sender, "seq": seq, "ts": time.time(), **fields}


def _pack(msg) -> bytes:
    return msgpack.packb(msg, use_bin_type=True)


def _padded(msg: dict, size: int) -> bytes:
    """``msg`` (otherwise valid) with a filler field so that it packs to exactly ``size`` bytes."""
    k = max(0, size - len(_pack(msg)))
    for _ in range(10):
        blob = _pack(dict(msg, pad=b"x" * k))
        if len(blob) == size:
            return blob
        k += size - len(blob)
    raise AssertionError("could not pad to size")


def _generic(kind: str, valid: dict, other_kind: str) -> list[tuple[str, bytes, str]]:
    """Malformed envelopes of any kind: (label, payload, the reason the receiver logs)."""
    from khgrl.common.wire.protocol import KINDS

    limit = KINDS[kind].MAX_BYTES

    return [
        ("garbage", b"\xc1\xc1\xc1 not msgpack \x00\xff", "not msgpack"),
        ("empty", b"", "not msgpack"),
        ("not a map", _pack([1, 2, 3]), "message is not a map"),
        ("schema version", _pack(dict(valid, v=2)), "schema version 2, expected the integer 1"),
        ("schema version 1.0", _pack(dict(valid, v=1.0)), "schema version 1.0, expected the integer 1"),
        ("wrong kind", _pack(dict(valid, kind=other_kind)), f"kind '{other_kind}' on a {kind} topic"),
        ("bad sender", _pack(dict(valid, sender="a/b")), "sender: bad identifier"),
        ("oversize", _padded(valid, limit + 1),
         # (an actor refuses weights longer than its own network's take, before decoding: issue 21)
         f"{limit + 1} bytes: the actor network's weights take at most" if kind == "weights" else
         f"{limit + 1} bytes exceeds the {kind} limit"),
    ]


def _transitions_fields(n: int = 4) -> dict:
    from khgrl.common.wire.protocol import pack_array

    rng = np.random.default_rng(1)
    return {
        "actor": "a0", "first_step": 0, "task": "0123456789abcdef",
        "obs": pack_array(rng.uniform(0, 1, (n, 5)).astype(np.float32)),
        "next_obs": pack_array(rng.uniform(0, 1, (n, 5)).astype(np.float32)),
        "action": pack_array(rng.uniform(-1, 1, (n, 2)).astype(np.float32)),
        "reward": pack_array(np.zeros(n, np.float32)),
        **{f: pack_array(np.zeros(n, np.uint8)) for f in ("terminated", "truncated", "intervened", "clipped")},
    }


def _hostile_transitions() -> list[tuple[str, bytes, str]]:
    from khgrl.common.wire.protocol import pack_array

    base = _transitions_fields()
    valid = _env_msg("transitions", sender="a0", seq=1, **base)
    bad = _generic("transitions", valid, "ack")

    def v(label, reason, **over):
        bad.append((label, _pack(dict(valid, **over)), reason))

    v("wrong shape", "obs: expected shape", obs=pack_array(np.zeros((4, 4), np.float32)))
    v("wrong dtype", "truncated: dtype '<f4' not in", truncated=pack_array(np.zeros(4, np.float32)))
    v("NaN", "reward: contains NaN or inf", reward=pack_array(np.array([0, np.nan, 0, 0], np.float32)))
    v("inf", "next_obs: contains NaN or inf", next_obs=pack_array(np.full((4, 5), np.inf, np.float32)))
    v("bytes vs shape", "action: 24 bytes do not match shape", action=dict(pack_array(np.zeros((4, 2), np.float32)),
                                                                            data=b"\0" * 24))
    v("rows mismatch", "intervened: 3 rows, expected 4", intervened=pack_array(np.zeros(3, np.uint8)))
    v("action out of box", "actions outside [-1, 1]", action=pack_array(np.full((4, 2), 1.5, np.float32)))
    v("flag not 0/1", "terminated: flags must be 0/1", terminated=pack_array(np.full(4, 2, np.uint8)))
    flags = ("terminated", "truncated", "intervened", "clipped")
    empty = {k: pack_array(np.zeros((0, 5) if k in ("obs", "next_obs") else (0, 2) if k == "action" else (0,),
                                    np.uint8 if k in flags else np.float32))
             for k in base if k not in ("actor", "first_step")}
    v("empty batch", "batch of 0 transitions", **empty)
    v("base_seq > seq", "base_seq 9 > seq 1", base_seq=9)
    v("missing field", "clipped: not an array map", clipped=None)
    v("negative first_step", "first_step: -1 < 0", first_step=-1)
    v("no task digest", "task: missing", task=None)
    return bad


def _hostile_acks() -> list[tuple[str, bytes, str]]:
    ack = _env_msg("ack", sender="learner", actor="a0", received=0, durable=0, trained=0, epoch="e", version=0)
    return _generic("ack", ack, "weights") + [
        ("received str", _pack(dict(ack, received="x")), "received: expected"),
        ("trained < 0", _pack(dict(ack, trained=-5)), "trained: -5 < 0"),
        ("bad stream", _pack(dict(ack, stream="a/b")), "stream: bad identifier"),
        ("missing epoch", _pack({k: v for k, v in ack.items() if k != "epoch"}), "epoch: expected"),
    ]


def _hostile_corrections(spoof_key: str) -> list[tuple[str, bytes, str]]:
    corr = _env_msg("correction", sender="evil", client="evil", actor="a0", active=True, p_h=[0.6, 0.58])
    return _generic("correction", corr, "frame") + [
        ("p_h NaN", _pack(dict(corr, p_h=[float("nan"), 0.5])), "p_h[0]: not finite"),
        ("p_h inf", _pack(dict(corr, p_h=[0.5, float("inf")])), "p_h[1]: not finite"),
        ("p_h shape", _pack(dict(corr, p_h=[0.5])), "p_h: expected a list of 2 numbers"),
        ("active str", _pack(dict(corr, active="yes")), "active: expected"),
        ("episode < 0", _pack(dict(corr, episode=-1)), "episode: -1 < 0"),
        ("bad actor id", _pack(dict(corr, actor="a 0")), "actor: bad identifier"),
        # a valid correction claiming to be the scripted client, on another client's key
        ("spoofed client", _pack(dict(corr, client="scripted", sender="scripted")),
         f"client 'scripted' published on {spoof_key}"),
    ]


def _hostile_frames() -> list[tuple[str, bytes, str]]:
    frame = _env_msg("frame", sender="a0", actor="a0", episode=HUMAN_EPISODE, t=10, phase=0.5, robot=[0.6, 0.5],
                     desired=[0.6, 0.5], mean=[0.6, 0.5], scale=[15.0, 15.0], intervening=False, task="passage-low_cov")
    return _generic("frame", frame, "episode") + [
        ("robot NaN", _pack(dict(frame, robot=[float("nan"), 0.5])), "robot[0]: not finite"),
        ("mean inf", _pack(dict(frame, mean=[float("inf"), 0.5])), "mean[0]: not finite"),
        ("phase > 1", _pack(dict(frame, phase=2.0)), "phase: 2.0 > 1.0"),
        ("mean shape", _pack(dict(frame, mean=[0.5, 0.5, 0.5])), "mean: expected a list of 2 numbers"),
        ("intervening str", _pack(dict(frame, intervening="no")), "intervening: expected"),
        ("episode < 0", _pack(dict(frame, episode=-1)), "episode: -1 < 0"),
    ]


def _hostile_controls() -> list[tuple[str, bytes, str]]:
    stop = _env_msg("control", sender="evil", command="stop")
    return _generic("control", stop, "ack") + [
        ("unknown command", _pack(dict(stop, command="reboot")), "unknown command 'reboot'"),
        ("command int", _pack(dict(stop, command=7)), "command: expected"),
        ("seq < 0", _pack(dict(stop, seq=-1)), "seq: -1 < 0"),
        ("ts str", _pack(dict(stop, ts="now")), "ts: expected"),
        ("ts NaN", _pack(dict(stop, ts=float("nan"))), "ts: "),  # logged reason "ts", as the str's
    ]


# who receives a control message on each target: (process, kind)
# (the launcher watches every control key: a command from another session on any of them is reported)
CONTROL_TARGETS = {"all": [("learner", "control"), ("actor", "control"), ("human", "control"), ("launcher", "control")],
                   "learner": [("learner", "control"), ("launcher", "control")],
                   "actor": [("actor", "control"), ("launcher", "control")],
                   "a0": [("actor", "control"), ("launcher", "control")],
                   "human": [("human", "control"), ("launcher", "control")]}


def _hostile_weights(real) -> list[tuple[str, bytes, str]]:
    """Weights messages the actor must refuse, built on the shapes of the learner's real weights ``real``."""
    from khgrl.common.wire.protocol import pack_array

    names = sorted(real.tensors)
    shapes = {k: tuple(v.shape) for k, v in real.tensors.items()}
    zeros = {k: pack_array(np.zeros(v, np.float32)) for k, v in shapes.items()}
    w = _env_msg("weights", sender="learner", version=10**6, epoch="evil", trained={"a0": 0}, tensors=zeros)
    first, second, third = names[0], names[1], names[2]  # distinct fields: distinct logged reasons
    wider = shapes[first][:-1] + (shapes[first][-1] + 1,)

    def tensors(**over) -> bytes:
        return _pack(dict(w, tensors=dict(zeros, **over)))

    return _generic("weights", w, "transitions") + [
        ("wrong tensor names", _pack(dict(w, tensors={f"evil.{k}": v for k, v in zeros.items()})),
         "do not match the actor network"),
        ("missing tensor", _pack(dict(w, tensors={k: v for k, v in zeros.items() if k != first})),
         "do not match the actor network"),
        ("wrong tensor shape", tensors(**{first: pack_array(np.zeros(wider, np.float32))}), "the actor network has"),
        ("NaN tensor", tensors(**{second: pack_array(np.full(shapes[second], np.nan, np.float32))}),
         f"tensors[{second}]: contains NaN or inf"),
        ("float64 tensor", tensors(**{third: pack_array(np.zeros(shapes[third], np.float64))}),
         f"tensors[{third}]: dtype '<f8' not in"),
        ("no tensors", _pack(dict(w, tensors={})), "tensors: "),  # same logged reason as the names
        ("version < 0", _pack(dict(w, version=-1)), "version: -1 < 0"),
        ("bad trained key", _pack(dict(w, trained={"a/0": 1})), "trained key: bad identifier"),
    ]


class _Observer:
    """A test client's view of the run: every process's latest status info and the number of a0's frames."""

    def __init__(self, keys) -> None:
        self.keys = keys
        self.status: dict[str, object] = {}
        self.frames = 0
        self.lock = threading.Lock()

    def on_status(self, sample) -> None:
        from khgrl.common.wire.messages import Status
        from khgrl.common.wire.protocol import ProtocolError, decode

        try:
            msg = decode(Status, sample.payload.to_bytes())
        except ProtocolError:  # our own hostile status messages
            return
        with self.lock:
            self.status[str(sample.key_expr)] = msg.info

    def on_frame(self, sample) -> None:
        self.frames += 1

    def rejects(self, role: str, ident: str) -> dict:
        with self.lock:
            info = self.status.get(self.keys.status(role, ident))
            return dict(info.rejects) if info is not None else {}

    def running(self) -> bool:
        """Frames from a0, and statuses of learner and actor that report no rejects."""
        seen = self.keys.status("learner", "learner") in self.status and self.keys.status("actor", "a0") in self.status
        return self.frames > 0 and seen and self.rejects("learner", "learner") == {} and \
            self.rejects("actor", "a0") == {}

    def all_rejects(self) -> dict[str, dict]:
        return {"learner": self.rejects("learner", "learner"), "actor": self.rejects("actor", "a0"),
                "human": self.rejects("human", "scripted")}


class _Attacker:
    """Sends hostile payloads and keeps what each receiving process must count and log."""

    def __init__(self, session, keys) -> None:
        self.s, self.keys = session, keys
        self.count: dict[tuple[str, str], int] = {}  # (process, kind) -> rejects
        self.reasons: set[tuple[str, str, str]] = set()  # (process, kind, logged reason)
        self.weights_sent = 0

    def send(self, key: str, payload: bytes, receivers: list[tuple[str, str]], reason: str,
             pause: float = 0.01) -> None:
        import zenoh

        self.s.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        for proc, kind in receivers:
            self.count[(proc, kind)] = self.count.get((proc, kind), 0) + 1
            if reason:
                self.reasons.add((proc, kind, reason))
        time.sleep(pause)

    def every_topic(self, real) -> None:
        k = self.keys
        for _, payload, reason in _hostile_transitions():  # the learner: on a0's key and on another actor's
            for actor in ("a0", "evil"):
                self.send(k.transitions(actor), payload, [("learner", "transitions")], reason)
        valid_tr = _pack(_env_msg("transitions", sender="a0", seq=0, **_transitions_fields()))
        self.send(k.transitions("evil"), valid_tr, [("learner", "transitions")],
                  f"actor 'a0' published on {k.transitions('evil')}")
        for _, payload, reason in _hostile_acks():
            self.send(k.ack("a0"), payload, [("actor", "ack")], reason)
        for _, payload, reason in _hostile_corrections(k.correction("evil")):
            self.send(k.correction("evil"), payload, [("actor", "correction")], reason)
        for _, payload, reason in _hostile_frames():  # the human subscribes to every actor's frames
            for actor in ("a0", "evil"):
                self.send(k.frame(actor), payload, [("human", "frame")], reason)
        for _, payload, reason in _hostile_controls():  # nothing here may stop, pause or checkpoint anything
            for target, receivers in CONTROL_TARGETS.items():
                self.send(k.control(target), payload, receivers, reason)
        self._launcher_topics()
        # weights (actor a0; RingChannel(1): spaced, and each sent twice, so none is overwritten unseen)
        for _, payload, reason in _hostile_weights(real):
            for _ in range(2):
                self.send(k.weights, payload, [], "", pause=0.25)
            self.weights_sent += 2
            self.reasons.add(("actor", "weights", reason))

    def _launcher_topics(self) -> None:
        """Malformed status and episode messages (the launcher's progress view)."""
        st = _env_msg("status", sender="evil", role="learner", info={"ingested": 1})
        for _, payload, _ in _generic("status", st, "control") + [("info not a map", _pack(dict(st, info="x")), "")]:
            self.send(self.keys.status("learner", "evil"), payload, [("launcher", "status")], "")
        epi = _env_msg("episode", sender="evil", actor="evil", stats={"episode": 1})
        for _, payload, _ in _generic("episode", epi, "status") + [
                ("episode 0", _pack(dict(epi, stats={"episode": 0})), "")]:
            self.send(self.keys.episode("evil"), payload, [("launcher", "episode")], "")

    def weight_reasons(self) -> int:
        return len({r for _, k, r in self.reasons if k == "weights"})

    def reported(self, got: dict[str, dict]) -> bool:
        """Whether the processes' status reports every reject sent to them (weights: at least one per reason)."""
        ok = all(got[p].get(k, 0) == c for (p, k), c in self.count.items() if p != "launcher")
        return ok and self.weight_reasons() <= got["actor"].get("weights", 0) <= self.weights_sent


def _learner_final_rejects(learner_log: str) -> dict:
    """The rejects by kind in the learner's last log line (``learner ID done: {...}; inbox dropped ...``)."""
    done = [ln for ln in learner_log.splitlines() if " done: {" in ln and "rejected" in ln]
    assert done, learner_log[-2000:]
    return ast.literal_eval(done[-1].split(" done: ", 1)[1].rsplit("; inbox dropped", 1)[0])["rejected"]


def _check_harmless(run_dir: Path, attack: _Attacker, err_text: str) -> None:
    """The run completed as if nothing had been sent, and every reject is counted and logged with its reason."""
    summary = read_json(run_dir / "summary.json")
    assert summary["exit_codes"] == {"router": 0, "learner": 0, "a0": 0, "human-scripted": 0}, summary
    launcher = {k: c for (p, k), c in attack.count.items() if p == "launcher"}
    assert summary["launcher_rejects"] == launcher, summary["launcher_rejects"]
    rows = _episodes_csv(run_dir)
    n = sum(int(r["steps"]) for r in rows)
    actor = read_json(run_dir / "actor-a0" / "summary.json")
    assert actor["episodes"] == 3 and actor["stopped_by"] is None and actor["unconfirmed_transitions"] == 0
    assert actor["corrections"]["holds"] == sum(int(r["interventions"]) for r in rows), actor["corrections"]
    assert int(next(r for r in rows if int(r["episode"]) == 1)["intervention_steps"]) == 0
    state, arrays = _checkpoint(run_dir)
    slots = _assert_exactly_once(state, arrays, "a0", n)  # nothing hostile got into the replay buffer
    assert state["total_ingested"] == n
    assert int(arrays["intervened"][slots].sum()) == sum(int(r["intervention_steps"]) for r in rows)
    # final counts by kind: the actor's summary and the learner's last log line
    for kind in ("ack", "correction", "control"):
        assert actor["rejects"].get(kind) == attack.count[("actor", kind)], (kind, actor["rejects"])
    assert attack.weight_reasons() <= actor["rejects"].get("weights", 0) <= attack.weights_sent, actor["rejects"]
    learner_log = (run_dir / "logs" / "learner.log").read_text()
    assert _learner_final_rejects(learner_log) == {"transitions": attack.count[("learner", "transitions")],
                                                   "control": attack.count[("learner", "control")]}
    # every category sent is visible, with its reason, in the receiving process's log (the launcher's: stderr)
    logs = {"learner": learner_log, "actor": (run_dir / "logs" / "a0.log").read_text(),
            "human": (run_dir / "logs" / "human-scripted.log").read_text(), "launcher": err_text}
    missing = [(p, k, r) for p, k, r in sorted(attack.reasons)
               if not any(f"rejected {k} message" in ln and r in ln for ln in logs[p].splitlines())]
    assert not missing, f"rejections not logged: {missing}"
    assert "Traceback" not in "".join(logs.values())


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_hostile_messages_on_every_topic_are_rejected_counted_and_harmless(tmp_path):
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Weights
    from khgrl.common.wire.protocol import Keys, decode

    run_dir, port, run = tmp_path / "run", free_port(), unique_run("evil")
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys(run)
    # --rate 30: 3 episodes take ~25 s whatever the machine, so the run outlives the attack (~10 s) and the status
    # reports after it (unpaced, a fast machine ended the run in the middle of the attack)
    argv = _up_argv(run_dir, port, run, *FAST, *FULL_UTD, "--episodes", "3", "--human-episodes", str(HUMAN_EPISODE),
                    "--no-progress", "--rate", "30")
    out_path, err_path = tmp_path / "up.stdout", tmp_path / "up.stderr"
    launcher = None
    view = _Observer(keys)
    try:
        with open(out_path, "w") as out, open(err_path, "w") as err:
            launcher = subprocess.Popen(argv, cwd=REPO, env=_env(), stdout=out, stderr=err, start_new_session=True)
        with open_client(endpoint, timeout=60) as s:
            subs = [s.declare_subscriber(keys.status("*", "*"), view.on_status),
                    s.declare_subscriber(keys.frame("a0"), view.on_frame)]
            try:
                wait_for(view.running, 120, "learner and actor running")
                wait_for(lambda: any(r.ok for r in s.liveliness().get(keys.alive("human", "*"), timeout=1.0)), 60,
                         "the human-input process")
                assert launcher.poll() is None, err_path.read_text()
                replies = [r.ok for r in s.get(keys.weights, timeout=5.0) if r.ok]
                assert replies, "no weights from the learner's queryable"
                real = decode(Weights, replies[0].payload.to_bytes())
                attack = _Attacker(s, keys)
                attack.every_topic(real)
                # the learner's weights queryable still answers (a query with a garbage payload)
                replies = [r.ok for r in s.get(keys.weights, payload=b"\xc1garbage", timeout=5.0) if r.ok]
                assert replies and decode(Weights, replies[0].payload.to_bytes()).version >= real.version
                # the processes report them in their status, by kind, while the run goes on
                try:
                    wait_for(lambda: attack.reported(view.all_rejects()), 90, "rejects reported in status")
                except AssertionError as exc:
                    raise AssertionError(f"{exc}\nexpected {attack.count}, weights {attack.weight_reasons()}.."
                                         f"{attack.weights_sent}\nstatus: {view.all_rejects()}") from None
                rc = launcher.wait(timeout=200)
            finally:
                for sub in subs:
                    sub.undeclare()
        err_text = err_path.read_text()
        assert rc == 0, f"khgrl up exited {rc}\n{out_path.read_text()}\n{err_text}"
        _check_harmless(run_dir, attack, err_text)
    finally:
        _cleanup(launcher, run_dir)


# ============================================================== schema-valid but odd messages to the launcher
@pytest.mark.integration
@pytest.mark.timeout(120)
@pytest.mark.parametrize("kind,progress", [("episode", False), ("status", True)],
                         ids=["episode-no-progress", "status-progress-view"])
def test_launcher_survives_odd_and_malformed_episode_and_status(tmp_path, kind, progress):
    """``khgrl up`` subscribes to every actor's episode messages and the learner's status. A malformed one is
    rejected (a string where a number belongs), and a schema-valid one with odd values (an unknown actor,
    huge or negative numbers) is shown as it is: neither crashes the launcher (docs/protocol.md: a receiver
    "never crashes on input"). Episode messages are formatted in both modes, the learner's status only by
    the live table (the default)."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import EpisodeReport, LearnerInfo, Status
    from khgrl.common.wire.protocol import Keys, encode

    run_dir, port, run = tmp_path / "run", free_port(), unique_run("evil")
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys(run)
    argv = _up_argv(run_dir, port, run, *FAST, "--episodes", "3", "--stop-timeout", "2",
                    *([] if progress else ["--no-progress"]))
    out_path, err_path = tmp_path / "up.stdout", tmp_path / "up.stderr"
    if kind == "status":
        info = LearnerInfo(id="evil", epoch="e", ingested=-5, iterations=10**15, gradient_steps=-1,
                           grad_steps_per_s=1e300, version=-7, pending_iterations=0, queue_depth=0, rejects={},
                           paused=True, checkpoints=0, next_seq={}, durable={}, duplicates={}, weights_queries=0)
        odd = encode(Status(role="learner", info=info), "evil", 0)
        malformed = _pack(_env_msg("status", role="learner", info={"ingested": "lots"}))
        key = keys.status("learner", "evil")
    else:
        odd = encode(EpisodeReport(actor="evil", stats={"episode": 10**12, "ret": -1e300, "success": True,
                                                        "intervention_steps": -4, "clipped_steps": 10**9,
                                                        "interventions": -1, "mean_abs_xi_h": 1e300}), "evil", 0)
        malformed = _pack(_env_msg("episode", actor="evil", stats={"episode": 1, "ret": "much", "success": "no"}))
        key = keys.episode("evil")
    launcher = None
    try:
        with open(out_path, "w") as out, open(err_path, "w") as err:
            launcher = subprocess.Popen(argv, cwd=REPO, env=_env(), stdout=out, stderr=err, start_new_session=True)
        with open_client(endpoint, timeout=60) as s:
            pub = s.declare_publisher(key)
            try:
                def matching() -> bool:
                    ms = pub.matching_status
                    return bool(getattr(ms, "matching", ms))

                wait_for(matching, 60, "the launcher's subscriber")
                assert launcher.poll() is None, err_path.read_text()
                pub.put(malformed)
                pub.put(odd)
                time.sleep(3.0)
                survived = launcher.poll() is None
            finally:
                pub.undeclare()
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGINT)  # Ctrl-C: a clean stop exits 130
        rc = launcher.wait(timeout=60)
        err_text = err_path.read_text()
        assert survived and rc == 130 and "Traceback" not in err_text, (
            f"khgrl up ({'live table' if progress else '--no-progress'}) died with exit code {rc} on {kind} "
            f"messages on {key}:\n{err_text[-2500:]}")
        summary = read_json(run_dir / "summary.json")
        assert summary["launcher_rejects"] == {kind: 1}, summary
        if kind == "episode":
            assert "[evil] episode 1000000000000: return" in out_path.read_text()
    finally:
        _cleanup(launcher, run_dir)
