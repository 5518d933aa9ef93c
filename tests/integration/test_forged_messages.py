"""The protocol checks that hold without access control, against real processes over a real router: while an actor
and a learner run, a separate Zenoh client (knowing only docs/protocol.md and what it can read on the router)
publishes (a) weights with the real tensor names and shapes, the learner's real epoch and version 10**9, (b) weights
of made-up epochs, (c) acks claiming batches the actor never sent. The actor never runs the forged weights, counts
every refusal, and the run completes with every transition stored exactly once -- its final flush asking the learner
for a checkpoint on its own ``actor/<id>/request`` key. Last, a ``stop`` from someone other than the launcher stops
the learner and is logged with its sender. (The same checks without processes: tests/unit/test_trust_checks.py.)
"""

from __future__ import annotations

import re
import time

import pytest

from helpers import ProcGroup, read_json, unique_run, wait_for

FAST = ["--scenario", "low_cov", "--method", "khgrl", "--learning-starts", "16"]
FORGED_VERSION = 10**9
SENDS = 20  # the actor's weights subscriber keeps only the newest sample (RingChannel(1)): a forged message can be
# overwritten by the next before the actor reads it, so each attack is sent again until the actor counts it


@pytest.mark.integration
@pytest.mark.timeout(180)
def test_forged_weights_and_acks_are_refused_and_nothing_is_lost(tmp_path):
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Ack, Control, Status, Transitions, Weights
    from khgrl.common.wire.protocol import Keys, decode, encode

    run, run_dir = unique_run("trust"), tmp_path / "run"
    keys = Keys(run)
    seen: dict = {"versions": []}

    def on_ack(sample) -> None:
        msg = decode(Ack, sample.payload.to_bytes())
        if msg.received < FORGED_VERSION:
            seen["ack"] = msg

    def on_transitions(sample) -> None:
        msg = decode(Transitions, sample.payload.to_bytes())
        seen["stream"], seen["last_seq"] = msg.stream, msg.envelope.seq

    def on_status(sample) -> None:
        info = decode(Status, sample.payload.to_bytes()).info
        seen["versions"].append(info.weights_version)
        seen["rejects"] = info.rejects.get("weights", 0)

    def send_until_counted(make, refusals: int, what: str, seq0: int) -> None:
        """Send ``make(i)`` every 0.3 s until the actor's status counts ``refusals`` more weights rejects, then
        wait 1.5 s (its status comes every second) so that what was still on its way is counted before the next."""
        want = seen.get("rejects", 0) + refusals
        for i in range(SENDS):
            if seen.get("rejects", 0) >= want:
                break
            assert actor.poll() is None, f"the actor ended before {what} was counted\n{actor.tail()}"
            s.put(keys.weights, encode(make(i), "learner", seq0 + i))
            time.sleep(0.3)
        wait_for(lambda: seen.get("rejects", 0) >= want, 5, f"the actor counting {what}")
        time.sleep(1.5)

    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "16", "--checkpoint-every", "0")
        actor = g.actor(run, ep, *FAST, "--episodes", "4", "--max-lead", "100000", "--rate", "60")
        with open_client(ep) as s:
            subs = [s.declare_subscriber(keys.ack("a0"), on_ack),
                    s.declare_subscriber(keys.transitions("a0"), on_transitions),
                    s.declare_subscriber(keys.status("actor", "a0"), on_status)]
            try:
                wait_for(lambda: "ack" in seen and seen["ack"].version >= 1 and max(seen["versions"], default=-1) >= 1,
                         90, "the actor running on trained weights", procs=[learner, actor])
                real = [decode(Weights, r.ok.payload.to_bytes()) for r in s.get(keys.weights, timeout=5.0) if r.ok]
                assert real and real[0].epoch == seen["ack"].epoch
                tensors, epoch = real[0].tensors, real[0].epoch
                # (a) the real epoch and tensors, an impossible version; (b) made-up epochs: held for a learner that
                # never comes, each displacing the one before (two refusals counted: forged weights of two epochs)
                send_until_counted(lambda i: Weights(version=FORGED_VERSION, trained={"a0": 10**6}, tensors=tensors,
                                                     epoch=epoch), 1, "(a)", 10**6)
                send_until_counted(lambda i: Weights(version=1, trained={}, tensors=tensors, epoch=f"forged{i}"),
                                   2, "(b)", 2 * 10**6)
                forged_ack = seen["ack"].replace(received=seen["last_seq"] + 10**6, durable=seen["last_seq"] + 10**6,
                                                 stream=seen["stream"])
                for i in range(3):  # (c) acks of batches never sent
                    s.put(keys.ack("a0"), encode(forged_ack, "learner", 3 * 10**6 + i))
                    time.sleep(0.05)
                rc = actor.wait(120)
                assert rc == 0, actor.tail()
                # a stop that is not the launcher's: obeyed, and logged with its sender
                s.put(keys.control("learner"), encode(Control(command="stop"), "tester", 0))
                assert learner.wait(60) == 0, learner.tail()
            finally:
                for sub in subs:
                    sub.undeclare()

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    assert 1 <= summary["weights"]["final_version"] < FORGED_VERSION, summary["weights"]
    assert max(seen["versions"]) < FORGED_VERSION
    assert summary["refused_acks"] == 3 and summary["rejects"]["ack"] == 3, summary["rejects"]
    assert summary["rejects"]["weights"] >= 3, summary["rejects"]  # (a), and (b) displaced or expired
    assert summary["episodes"] == 4 and summary["unconfirmed_transitions"] == 0
    assert summary["durable"] == summary["last_seq"]  # the flush's checkpoint request reached the learner
    log = (run_dir / "actor-a0" / "actor.log").read_text()
    assert f"version {FORGED_VERSION} of learner epoch {epoch} is implausible" in log
    assert re.search(r"of learner epoch forged\d+: no learner of that epoch appeared", log), log[-3000:]
    assert "ack claims batches beyond the highest seq sent" in log
    assert "replacing the loaded weights" not in log  # no forged weights were ever loaded
    learner_log = (run_dir / "learner" / "learner.log").read_text()
    assert "control stop from 'tester' on" in learner_log and "not from the launcher" in learner_log
    assert "rejected control" not in learner_log
    check = provenance_check(run_dir)
    assert check["lost"] == 0 and check["duplicated"] == 0 and check["stored"] == summary["transitions"], check
