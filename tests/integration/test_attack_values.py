"""Issue 21, "values are bounded": an authenticated actor id sends extreme values under ``khgrl up --secure``.

The run's certificates include an extra actor id, ``x9``, that no process of the run uses: its certificate is
issued into the run's certificate directory between two parts of one run (``khgrl up --resume --secure`` makes the
router's access control from every identity there). During the second part this test publishes, from a session
holding ``actor-x9``'s certificate and on x9's own keys only,

(a) one batch of 8 transitions with reward 3e38 (a finite float32), and a checkpoint request;
(b) for 3 seconds, batches with rewards and observations of +-3e38;
(c) a batch of ordinary values without the task digest.

Before issue 21, (a) made the learner exit 1 within 2.2 s (NaN in the policy) and its checkpoint crashed every
resumed learner. Now the learner refuses each batch (status ``rejects``: ``values`` for (a) and (b), ``transitions``
for (c), with log lines naming x9), rolls nothing back because nothing poisonous reached training, stays under
1 GB, stores the honest actor a0's transitions exactly once, and the run ends by itself with exit code 0; a learner
resumed from the run's checkpoint starts, trains and is healthy.
"""

from __future__ import annotations

import ast
import re
import time

import numpy as np
import pytest

from helpers import ProcGroup, actor_signer, pid_alive, read_json, wait_for
from launch import KGRL, Launcher, _run

pytestmark = pytest.mark.integration

ARGS = [*KGRL, "--seed", "5", "--rate", "40", "--secure"]  # (40 Hz: the attack's 9 s lie inside part 2 anywhere)
EXTREME = 3e38


def _session(run_dir, cn: str, endpoint: str):
    from khgrl.common.delivery.transport import _open
    from khgrl.common.delivery.zenoh_config import build_config

    conf = build_config("client", [], [endpoint], 3000, run_dir / "certs" / "zenoh" / f"{cn}.json5")
    return _open(conf, lambda: False, 20, cn)


def _batch(task, seq: int, *, reward: float = 0.0, obs: float | None = None, digest: bool = True,
           key: bytes | None = None) -> bytes:
    """Batch ``seq`` of actor x9 (8 transitions of the task's sizes), encoded and signed with ``key`` (the run's:
    an actor process holds it); without ``digest``: its map without the task field (which ``encode`` refuses to
    make)."""
    import msgpack
    from khgrl.common.delivery import data_keys
    from khgrl.common.wire.messages import Transitions
    from khgrl.common.wire.protocol import encode

    n = 8
    o = np.full((n, task.obs_dim), 0.5 if obs is None else obs, np.float32)
    z = np.zeros(n, np.uint8)
    msg = Transitions(actor="x9", first_step=n * seq, obs=o, next_obs=o.copy(),
                      action=np.zeros((n, task.out_dim), np.float32), reward=np.full(n, reward, np.float32),
                      terminated=z, truncated=z, intervened=z, clipped=z, base_seq=0, stream="x9stream",
                      task=task.digest)
    payload = encode(data_keys.sign_batch(msg, key, seq), "x9", seq)
    if digest:
        return payload
    m = msgpack.unpackb(payload, raw=False)
    del m["task"]
    return msgpack.packb(m, use_bin_type=True)


def _attack(up: Launcher, runtime: dict, task) -> tuple[list, int]:
    """(a), (b), (c) from actor-x9's session; returns the learner's status infos seen meanwhile and how many
    extreme batches were sent. Asserts the learner is alive after two training iterations that follow (a) (before
    the fix the first one made the policy NaN and the learner exit 1)."""
    from khgrl.common.wire.messages import Control, Status
    from khgrl.common.wire.protocol import Keys, decode, encode

    keys = Keys(runtime["run"])
    infos: list = []
    s = _session(up.run_dir, "actor-x9", runtime["endpoint"])
    key = actor_signer(up.run_dir, "x9")  # the worst case: x9 holds the run's key and its own role key, as an actor
    sub = s.declare_subscriber(keys.status("learner"), lambda m: infos.append(decode(Status, m.payload.to_bytes())))
    try:
        wait_for(lambda: infos, 120, "the learner's status", interval=0.2)
        pids = wait_for(lambda: (p := read_json(up.run_dir / "pids.json"))["launcher"] == up.proc.pid and p, 60,
                        "this part's pids.json")
        learner_pid = pids["children"]["learner"]
        at = infos[-1].info.iterations
        s.put(keys.transitions("x9"), _batch(task, 0, reward=EXTREME, key=key))  # (a)
        s.put(keys.request("x9"), encode(Control(command="checkpoint"), "x9", 0))

        def trained_on() -> bool:  # two more training iterations (which would sample the batch had it been stored)
            assert pid_alive(learner_pid) and up.proc.poll() is None, "the learner died of one batch of reward 3e38"
            return infos[-1].info.iterations >= at + 2

        wait_for(trained_on, 120, "two training iterations after (a)", interval=0.2)
        seq, t_end = 1, time.monotonic() + 3.0  # (b)
        while time.monotonic() < t_end:
            sign = 1.0 if seq % 2 else -1.0
            s.put(keys.transitions("x9"), _batch(task, seq, reward=sign * EXTREME, obs=-sign * EXTREME, key=key))
            seq += 1
            time.sleep(0.02)
        for k in range(3):  # (c): three, so that one gets past the inbox's cap for ids not admitted
            time.sleep(0.3)
            s.put(keys.transitions("x9"), _batch(task, seq + k, digest=False, key=key))
        time.sleep(2.0)
        assert pid_alive(learner_pid), "the learner died under sustained +-3e38"
        return list(infos), seq
    finally:
        sub.undeclare()
        s.close()


def _resumed_learner_is_healthy(tmp_path, run_dir, run: str, total: int) -> None:
    """A learner resumed from the run's checkpoint (on a router of its own) starts, publishes a healthy status
    holding the checkpoint's transitions, and stops cleanly."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Status
    from khgrl.common.wire.protocol import Keys, decode

    with ProcGroup(tmp_path / "resume") as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "64", "--resume", run_dir=run_dir)
        wait_for(lambda: "ready (epoch" in learner.tail(), 120, "the resumed learner", procs=[learner])
        seen: list = []
        with open_client(ep, 3000) as s:
            sub = s.declare_subscriber(Keys(run).status("learner"),
                                       lambda m: seen.append(decode(Status, m.payload.to_bytes()).info))
            wait_for(lambda: seen, 30, "the resumed learner's status", procs=[learner])
            sub.undeclare()
        info = seen[-1]
        assert info.ingested == total and info.rollbacks == 0 and info.rss_mb < 1024, info
        assert learner.stop(60) == 0, learner.tail()


@pytest.mark.timeout(900)
def test_extreme_values_from_an_authenticated_actor_are_refused(tmp_path):
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.common.delivery.task_link import load_task_file
    from khgrl.deploy.run.secure import issue_identities

    run_dir = tmp_path / "run"
    part1 = _run(run_dir, *ARGS, "--episodes", "1", timeout=400)
    assert part1.returncode == 0, f"part 1 exited {part1.returncode}\n{part1.stdout}\n{part1.stderr}"
    issue_identities(run_dir / "certs", [("actor", "x9")])  # the run's certificates include actor-x9
    task = load_task_file(run_dir / "learner" / "task.msgpack")
    up = Launcher(tmp_path, run_dir, "--resume", "--secure", "--episodes", "3", "--no-progress")
    try:
        runtime = wait_for(lambda: (r := read_json(run_dir / "config.json")["runtime"])["resumed"] and r, 120,
                           "part 2's config.json")
        assert runtime["secure"]
        infos, extreme = _attack(up, runtime, task)
        rc = up.proc.wait(timeout=400)
        assert rc == 0, f"the run exited {rc}\n{up.stdout}\n{up.stderr}"
    finally:
        up.cleanup()
    summary = read_json(run_dir / "summary.json")
    assert summary["stopped_by"] is None and not summary["failed"] and set(summary["exit_codes"].values()) == {0}
    log = (run_dir / "logs" / "learner.log").read_text()
    done = ast.literal_eval(re.findall(r"learner learner done: (\{.*\}); inbox", log)[-1])
    refused = done["rejected"]
    # every batch of x9 refused (or dropped over the inbox's cap for ids not admitted, which it never was; or, before
    # it was decoded, over its sender's budget: 64 batches, then 10 a second, for an id never stored)
    assert refused["values"] >= 1 and refused["transitions"] >= 1, done
    assert refused["values"] + refused["transitions"] + refused.get("over_budget", 0) + done["not_admitted_dropped"] \
        == extreme + 3, (done, extreme)
    assert done["rollbacks"] == 0 and max(i.info.rss_mb for i in infos) < 1024
    assert "rejected values message on" in log and "actor x9 batch 0: reward[0] = 3e+38 is outside" in log
    assert "actor/x9/transitions" in log and "task: missing" in log
    state = read_json(run_dir / "learner" / "checkpoint" / "state.json")
    assert set(state["actors"]) == {"a0"}, f"the learner admitted {sorted(state['actors'])}"
    acct = provenance_check(run_dir)
    assert acct["lost"] == 0 and acct["duplicated"] == 0 and acct["produced"] > 0, acct
    _resumed_learner_is_healthy(tmp_path, run_dir, runtime["run"], state["total_ingested"])
