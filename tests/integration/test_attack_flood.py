"""Issue 34 (7), cheap floods: an authenticated actor id publishes small, valid, signed, in-order batches as fast as
it can while the honest actor a0 runs as fast as flow control allows (``--rate 0``: a0 waits for the learner's
training, so every iteration the learner spends elsewhere costs a0 steps) under ``khgrl up --secure``.

``khgrl up`` issues a certificate for one extra actor id, ``f9`` (as test_attack_shares does for its attackers).
After a quiet phase, ``f9`` publishes pre-signed 8-row batches (a0's own rows, rolled: each one different; seq 0, 1,
2, ... in order, as the issue's flood: 43,132 in 25 s) for :data:`FLOOD_S` seconds, then a second quiet phase; then
``khgrl stop``. A monitor session records a0's status (steps) and the learner's; a0's flooded rate is compared
with the mean of the two quiet phases around it (the machine's load drifts).

Before the per-sender budget (main at ``696d564``): every batch was decoded, its signature checked and ordered; the
in-order ones were stored up to the lead cap and trained on first-come first-served, so a0 waited behind ``f9``'s
iterations: a0 at 0.09 of its quiet rate in the issue (21.6 -> 2.5 steps/s), 0.06-0.10 in this test; no
``over_budget`` reject. Now (:mod:`khgrl.common.delivery.admission`) each sender's batches pass its token bucket
in the Zenoh callback, before they are copied, decoded or checked; a sender whose batches are refused over its
budget stores nothing while it floods. Asserted: most of the flood refused as ``over_budget``, ``f9`` stored at
most its lead cap, a0's rate under the flood at least :data:`MIN_RATIO` of its quiet rate, the run stops cleanly
(exit 0), a0's transitions stored exactly once.
"""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest
from test_attack_shares import Watch, _session

import launch
from helpers import FULL_UTD, actor_signer, read_json, wait_for
from launch import FAST, Launcher, up_with_actor_certs

pytestmark = pytest.mark.integration

ATTACKER = "f9"
# a cap the test never reaches (it stops the run once the flood and the quiet after it are measured): 20 episodes
# ended in 33 s on a faster machine, before the test had stopped it
ARGS = [*FAST, *FULL_UTD, "--method", "kgrl", "--human", "none", "--episodes", "500", "--rate", "0", "--secure"]
QUIET_S, FLOOD_S = 8.0, 10.0
FLOOD_PER_S = 1725  # the rate: 43,132 batches in 25 s
# the issue's target is 0.8; a0's rate on the 2 shared cores of the development machine moves by +-30 % from one
# window to the next (docs/attacks.md), so the test asks for a margin below it (main: 0.06-0.10)
MIN_RATIO = 0.6
UP_WITH_ATTACKER = up_with_actor_certs((ATTACKER,))


def _flood_payloads(template, keys_of, n: int, task: str) -> list[bytes]:
    """``n`` encoded, signed, in-order batches of ``f9`` (8 rows each: a0's batch, rolled)."""
    from khgrl.common.delivery import data_keys
    from khgrl.common.wire.messages import Transitions
    from khgrl.common.wire.protocol import encode

    names = ("obs", "next_obs", "action", "reward", "terminated", "truncated", "intervened", "clipped")
    rows = template.n
    out = []
    for seq in range(n):
        arrays = {name: np.roll(getattr(template, name), seq % rows, axis=0) for name in names}
        arrays["reward"] = arrays["reward"] + np.float32(1e-3 * (seq % 997))  # (each batch different content)
        m = Transitions(actor=ATTACKER, first_step=rows * seq, stream=f"{ATTACKER}-flood", task=task, base_seq=0,
                        **arrays)
        out.append(encode(data_keys.sign_batch(m, keys_of, seq), ATTACKER, seq))
    return out


def _flood(session, key: str, payloads: list[bytes]) -> tuple[int, float, float]:
    """Publish ``payloads`` at up to :data:`FLOOD_PER_S` for :data:`FLOOD_S`; (sent, start, end)."""
    pub = session.declare_publisher(key)
    t0 = time.monotonic()
    i = 0
    while i < len(payloads) and time.monotonic() - t0 < FLOOD_S:
        pub.put(payloads[i])
        i += 1
        if i % 64 == 0:
            time.sleep(max(0.0, t0 + i / FLOOD_PER_S - time.monotonic()))
    t1 = time.monotonic()
    pub.undeclare()
    return i, t0, t1


def _stop(run_dir) -> None:
    """``khgrl stop RUN_DIR``: the actors end (their batches flushed), then ``khgrl up`` does."""
    done = subprocess.run([*launch.UP[:-1], "stop", str(run_dir)], env=launch._env(), capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, (done.stdout, done.stderr)


def _grad_rate(watch: Watch, t0: float, t1: float) -> float:
    """The learner's gradient steps a second between ``t0`` and ``t1`` (from its status)."""
    infos = watch.learner_between(t0, t1)
    return (infos[-1]["gradient_steps"] - infos[0]["gradient_steps"]) / max(t1 - t0, 1e-9) if len(infos) > 1 else 0.0


@pytest.mark.timeout(600)
def test_a_flood_of_small_signed_batches_costs_the_honest_actor_little(tmp_path, monkeypatch):
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.common.delivery.task_link import TASK_FILE, load_task_file
    from khgrl.common.wire.messages import Transitions
    from khgrl.common.wire.protocol import Keys, decode

    run_dir = tmp_path / "run"
    monkeypatch.setattr(launch, "UP", UP_WITH_ATTACKER)
    up = Launcher(tmp_path, run_dir, *ARGS)
    try:
        up.wait_line("khgrl up: run ", 120)
        runtime = read_json(run_dir / "config.json")["runtime"]
        keys, ep = Keys(runtime["run"]), runtime["endpoint"]
        monitor = _session(run_dir, "monitor", ep)
        watch = Watch(monitor, keys)

        def stepping() -> bool:
            assert up.proc.poll() is None, f"khgrl up exited {up.proc.returncode}\n{up.stdout}\n{up.stderr}"
            return bool(watch.a0) and watch.a0[-1][1] >= 100  # past learning_starts (64): training goes

        wait_for(stepping, 300, "a0 past learning_starts")
        task = load_task_file(run_dir / "learner" / TASK_FILE)
        with watch.lock:
            template = decode(Transitions, watch.batches[-1])
        payloads = _flood_payloads(template, actor_signer(run_dir, ATTACKER), int(FLOOD_PER_S * FLOOD_S),
                                   task.digest)
        attacker = _session(run_dir, f"actor-{ATTACKER}", ep)
        t0 = time.monotonic()
        time.sleep(QUIET_S)
        before = (t0, time.monotonic())
        try:
            sent, f0, f1 = _flood(attacker, keys.transitions(ATTACKER), payloads)
        finally:
            attacker.close()
        time.sleep(QUIET_S)
        after = (f1, time.monotonic())
        _stop(run_dir)
        rc = up.proc.wait(timeout=300)
        watch.close()
        monitor.close()
        # (khgrl up exits 1 when stopped from elsewhere; every process's own exit code is asserted below)
        assert rc == 1 and "stopped by a stop command" in up.stderr, f"khgrl up exited {rc}\n{up.stdout}\n{up.stderr}"
    finally:
        up.cleanup()

    quiet = (watch.rate(*before) + watch.rate(*after)) / 2
    under = watch.rate(f0, f1)
    rejects = watch.learner[-1][1]["rejects"]
    report = {"sent": sent, "flood_s": round(f1 - f0, 1), "a0_quiet_before": round(watch.rate(*before), 2),
              "a0_flooded": round(under, 2), "a0_quiet_after": round(watch.rate(*after), 2),
              "ratio": round(under / quiet, 3),
              "grad_steps_per_s": [round(_grad_rate(watch, *w), 1) for w in (before, (f0, f1), after)],
              "rejects": rejects, "rss_mb_max": max(i["rss_mb"] for i in watch.learner_between(f0, f1))}
    print("flood report:", report, flush=True)
    assert sent >= 0.5 * FLOOD_PER_S * FLOOD_S, report  # (the flood was one)
    assert rejects.get("over_budget", 0) >= sent // 2, report
    assert under >= MIN_RATIO * quiet, report

    summary = read_json(run_dir / "summary.json")
    assert not summary["failed"] and set(summary["exit_codes"].values()) == {0}, summary
    acct = provenance_check(run_dir)
    assert acct["lost"] == 0 and acct["duplicated"] == 0 and acct["produced"] > 0, acct
    state = read_json(run_dir / "learner" / "checkpoint" / "state.json")
    assert state["actors"]["a0"]["ingested"] == acct["produced"], (state["actors"], acct)
    # f9 stores what its lead cap (--max-lead 8 plus a batch) and training let through while its first burst lasts
    # (64 batches as a guest, then a member's: ~0.15 s at the flood's rate), then nothing (main: 13,122 batches
    # dropped over the held-bytes caps, the rest stored at the lead cap's pace)
    assert state["actors"].get(ATTACKER, {}).get("ingested", 0) <= 8 * template.n, state["actors"]
