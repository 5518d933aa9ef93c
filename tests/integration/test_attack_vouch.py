"""Issue 34, point 6: the human-data exemption is not a door. Real processes in plain mode with the run's key and
role keys (as ``khgrl up`` makes them): a router, the learner, actor a0 (KhGRL) and the scripted human, which
drives a0's first episode in lock-step with signed corrections.

The forger ``f1`` holds a real actor key (``actor:f1``) and the run's key, and signs each batch exactly as an actor
process would. Once a0's human-driven batches are out it publishes on its own stream:

* 12 batches of 8 transitions flagged ``intervened`` (human-driven) without a human's signature: 96 rows;
* 6 of a0's human-driven batches, as a monitor receives them, with one reward changed by one ulp (a new digest for
  the replay guard), their evidence copied as it is.

After: f1's 96 rows are stored as ordinary data (0 of them prior, counted ``unvouched``), the 6 replays are
refused (``replayed``), and a0's human-driven rows (80 steps) are all prior data in the learner's final checkpoint.
Before (main at 696d564, measured with this test): every row flagged human-driven was prior data and a batch of
them exempt from the replay guard -- f1's 96 rows and the 48 of its replays were stored as prior data (144 of
f1's 144 stored rows), nothing refused.
"""

from __future__ import annotations

import csv
import threading
import time

import numpy as np
import pytest

from helpers import ProcGroup, read_json, unique_run, wait_for
from launch import FAST

pytestmark = pytest.mark.integration

FORGED, REPLAYS, N = 12, 6, 8
A0 = ["--scenario", "low_cov", "--method", "khgrl", "--episodes", "2", "--rate", "200", "--learning-starts",
      "100000", "--id", "a0"]


class _Watch:
    """a0's batches (those with intervened rows apart) and the learner's status, as a monitor sees them."""

    def __init__(self, session, keys) -> None:
        from khgrl.common.wire.messages import Status, Transitions
        from khgrl.common.wire.protocol import decode

        self.lock = threading.Lock()
        self.human: dict[int, object] = {}  # seq -> a0's batch of human-driven rows only
        self.any = None
        self.learner = None

        def on_batch(sample) -> None:
            msg = decode(Transitions, sample.payload.to_bytes())
            with self.lock:
                self.any = msg
                if msg.intervened.all():
                    self.human[msg.envelope.seq] = msg

        def on_status(sample) -> None:
            msg = decode(Status, sample.payload.to_bytes())
            if msg.role == "learner":
                self.learner = msg.info

        self.subs = [session.declare_subscriber(keys.transitions("a0"), on_batch),
                     session.declare_subscriber(keys.status("learner", "*"), on_status)]


def _f1_batches(watch: _Watch) -> list:
    """f1's stream: FORGED batches flagged human-driven (a0's content, rewards shifted: new to the replay guard),
    then REPLAYS of a0's human-driven batches with one reward one ulp up."""
    with watch.lock:
        base, human = watch.any, [watch.human[s] for s in sorted(watch.human)][:REPLAYS]
    out = []
    for i in range(FORGED):
        out.append(dict(obs=base.obs[:1].repeat(N, 0), next_obs=base.next_obs[:1].repeat(N, 0),
                        action=base.action[:1].repeat(N, 0), reward=np.full(N, 0.125 * (i + 1), np.float32),
                        vouch=None))
    for m in human:
        reward = m.reward.copy()
        reward[0] = np.nextafter(reward[0], np.float32(np.inf))
        out.append(dict(obs=m.obs, next_obs=m.next_obs, action=m.action, reward=reward,
                        vouch=getattr(m, "vouch", None)))
    return out


def _publish_f1(session, keys, run_dir, watch: _Watch) -> int:
    from khgrl.common.delivery import data_keys, run_key
    from khgrl.common.delivery.data_keys import DataKeys
    from khgrl.common.delivery.role_keys import load_private
    from khgrl.common.wire.messages import Transitions
    from khgrl.common.wire.protocol import encode

    f1 = DataKeys(run=run_key.load(run_dir), kid="actor:f1", private=load_private(run_dir, "actor:f1"))
    task = watch.any.task
    sent = 0
    for seq, fields in enumerate(_f1_batches(watch)):
        n = len(fields["reward"])
        vouch = fields.pop("vouch")
        extra = {"vouch": vouch} if vouch else {}  # (main has no vouch field)
        msg = Transitions(actor="f1", first_step=N * seq, terminated=np.zeros(n, np.uint8),
                          truncated=np.zeros(n, np.uint8), intervened=np.ones(n, np.uint8),
                          clipped=np.zeros(n, np.uint8), base_seq=0, stream="f1-stream", task=task, **fields, **extra)
        session.put(keys.transitions("f1"), encode(data_keys.sign_batch(msg, f1, seq), "f1", seq))
        sent += n
        time.sleep(0.05)
    return sent


def _stored(run_dir) -> dict[str, tuple[int, int]]:
    """Per actor id, (rows stored, rows stored as prior data) in the learner's final checkpoint."""
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    ck = run_dir / "learner" / "checkpoint"
    state, arrays = read_json(ck / "state.json"), load_checkpoint_arrays(ck)
    codes, iv = arrays["provenance_actor"], arrays["intervened"].reshape(-1)
    out = {}
    for actor in ("a0", "f1"):
        mine = np.isin(codes, [c for c, e in enumerate(state["codes"]) if e["actor"] == actor])
        out[actor] = (int(mine.sum()), int(iv[mine].sum()))
    return out


@pytest.mark.timeout(300)
def test_an_actor_key_makes_no_human_data_and_replays_no_human_words(tmp_path):
    from khgrl.common.delivery import run_key
    from khgrl.common.delivery.control_sign import OPERATOR, ControlSigner
    from khgrl.common.delivery.role_keys import make_run_keys
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys

    run, run_dir = unique_run("vouch"), tmp_path / "run"
    keys = Keys(run)
    run_key.create(run_dir)  # as khgrl up does: the run's key and a key per role
    make_run_keys(run_dir, [("learner", "learner"), ("actor", "a0"), ("actor", "f1"), ("human", "scripted")],
                  fresh=True)
    assert FAST  # (the flags of the other tests: this one spells its own out)
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "100000", "--checkpoint-every", "0")
        human = g.human(run, ep, "scripted", "--scenario", "low_cov", "--human-episodes", "1", "--run-dir",
                        str(run_dir))
        time.sleep(1.0)  # (the human's subscription first: it announces lock-step for episode 1)
        a0 = g.actor(run, ep, *A0)
        with open_client(ep) as s:
            watch = _Watch(s, keys)
            try:
                wait_for(lambda: len(watch.human) >= REPLAYS and watch.learner is not None
                         and watch.learner.next_seq.get("a0", 0) > max(watch.human), 120,
                         "a0's human-driven batches stored", procs=[learner, a0, human])
                sent = _publish_f1(s, keys, run_dir, watch)
                wait_for(lambda: watch.learner.next_seq.get("f1", 0) >= FORGED + REPLAYS, 60,
                         "f1's batches taken", procs=[learner])
                assert a0.wait(180) == 0, a0.tail()
                stop = ControlSigner.load(run_dir, OPERATOR)
                s.put(keys.control("learner"), stop.payload(keys.control("learner"), "stop", "tester", 1))
                assert learner.wait(60) == 0, learner.tail()
                rejects = dict(watch.learner.rejects)
            finally:
                for sub in watch.subs:
                    sub.undeclare()
        human.stop(30)
    stored = _stored(run_dir)
    with open(run_dir / "actor-a0" / "episodes.csv") as f:
        a0_steps = sum(int(r["intervention_steps"]) for r in csv.DictReader(f))
    print(f"f1 sent {sent} rows flagged human-driven: stored {stored['f1'][0]}, as prior data {stored['f1'][1]}; "
          f"learner rejects {rejects}; a0: {stored['a0'][1]} prior rows of {a0_steps} human-driven steps")
    assert stored["f1"] == (FORGED * N, 0), stored  # (before: (144, 144))
    assert rejects.get("replayed", 0) == REPLAYS and rejects.get("unvouched", 0) == FORGED, rejects
    assert a0_steps > 0 and stored["a0"][1] == a0_steps, (stored, a0_steps)
