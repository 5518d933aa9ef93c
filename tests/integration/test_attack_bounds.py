"""Issue 34 point 5, "bounds far from the task": an actor that holds the run's keys sends rewards at 0.999 of the
old default bound.

The passage world's rewards stay within +-220 (+200 at the goal, -10 in the obstacle, -10 against a wall) plus the
action cost (at most 73.7): its learner's reward bound is 293.7. Before the fix a task stated no bound and got
1e6: the learner's bound was 1,000,073. During a ``khgrl up`` run (low_cov, KGRL, 2 episodes) this test publishes,
from a session of its own and signed as an actor process signs (the run's key and a role key of its own, actor id
``x9``), :data:`FORGED` batches of 8 transitions whose reward is 0.999 x 1,000,073 (observations as the passage
world's: 0.5), right after the learner is up, so every training iteration can sample them.

Before (the unchanged code, 696d564): all 24 forged batches were stored (values refused: 0, ``x9`` admitted:
the test fails there) and the critic's largest |Q| on a0's own stored transitions at the end of the run (78
iterations) was 2.09e4, a thousand times the 19.6 of this run now (Q_max = 2 x 293.7 / (1 - 0.99) =
58,746 is the most any reward within the task's bound allows, twice).
Now: the built-in task states its bounds, so every forged batch is refused (``rejected: values`` = 24, x9 never
admitted), nothing is rolled back (``rollbacks`` and ``q_rollbacks`` 0), a0's transitions are stored exactly once,
the critic's |Q| on a0's states stays in the task's range (19.6), and ``config.json`` says where the bounds came
from.
"""

from __future__ import annotations

import ast
import re
import time

import numpy as np
import pytest

from helpers import actor_signer, read_json, wait_for
from launch import KGRL, Launcher

pytestmark = pytest.mark.integration

OLD_BOUND = 1e6 + 73.728  # the passage learner's reward bound before: the 1e6 default plus the action cost
REWARD = 0.999 * OLD_BOUND
R_MAX = 220.0 + 73.728  # the passage world's reward bound as the learner holds it now (stated 220 + action cost)
GAMMA = 0.99
Q_MAX = 2 * R_MAX / (1 - GAMMA)  # 58,746
FORGED = 24


def _forged(task, seq: int, key) -> bytes:
    """Forged batch ``seq`` of actor x9: 8 transitions of the task's sizes, reward :data:`REWARD`, signed."""
    from khgrl.common.delivery import data_keys
    from khgrl.common.wire.messages import Transitions
    from khgrl.common.wire.protocol import encode

    n = 8
    o = np.full((n, task.obs_dim), 0.5, np.float32)
    z = np.zeros(n, np.uint8)
    msg = Transitions(actor="x9", first_step=n * seq, obs=o, next_obs=o.copy(),
                      action=np.zeros((n, task.out_dim), np.float32), reward=np.full(n, REWARD, np.float32),
                      terminated=z, truncated=z, intervened=z, clipped=z, base_seq=0, stream="x9stream",
                      task=task.digest)
    return encode(data_keys.sign_batch(msg, key, seq), "x9", seq)


def _attack(up: Launcher, runtime: dict, task) -> None:
    """Once the learner publishes its status: :data:`FORGED` batches of x9, 50 ms apart."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.messages import Status
    from khgrl.common.wire.protocol import Keys, decode

    keys = Keys(runtime["run"])
    infos: list = []
    key = actor_signer(up.run_dir, "x9")  # what an actor process signs with: the run's key and its role key
    with open_client(runtime["endpoint"], 3000) as s:
        sub = s.declare_subscriber(keys.status("learner"),
                                   lambda m: infos.append(decode(Status, m.payload.to_bytes())))
        wait_for(lambda: infos, 120, "the learner's status", interval=0.2)
        for seq in range(FORGED):
            s.put(keys.transitions("x9"), _forged(task, seq, key))
            time.sleep(0.05)
        sub.undeclare()


def _q_on_a0(run_dir, task) -> float:
    """The largest |Q| of the run's final critic (every critic and quantile) on a0's stored transitions."""
    from khgrl.common.config.settings import TQCSettings
    from khgrl.learner.tqc import TQCAlgorithm

    algo = TQCAlgorithm.load(run_dir / "learner" / "checkpoint", task, TQCSettings(), "cpu")
    rb, model = algo.buffer, algo.model
    assert model.gamma == pytest.approx(GAMMA)
    state = read_json(run_dir / "learner" / "checkpoint" / "state.json")
    rows = np.flatnonzero(rb.provenance_actor[:rb.pos] == state["actors"]["a0"]["code"])
    import torch

    with torch.no_grad():
        q = model.critic(torch.as_tensor(rb.observations[rows, 0]), torch.as_tensor(rb.actions[rows, 0]))
    return float(q.abs().max())


@pytest.mark.timeout(600)
def test_rewards_at_the_old_default_bound_are_refused(tmp_path):
    from khgrl.benchmarks.scale import provenance_check
    from khgrl.common.delivery.task_link import load_task_file

    run_dir = tmp_path / "run"
    up = Launcher(tmp_path, run_dir, *KGRL, "--seed", "5", "--episodes", "2",
                  "--rate", "50")  # ~10 s of stepping: the run outlives the attack on a fast machine too
    try:
        runtime = wait_for(lambda: (run_dir / "config.json").is_file() and read_json(run_dir / "config.json")
                           ["runtime"], 120, "config.json")
        task = wait_for(lambda: (p := run_dir / "learner" / "task.msgpack").is_file() and load_task_file(p), 60,
                        "the run's task file")
        _attack(up, runtime, task)
        rc = up.proc.wait(timeout=400)
        assert rc == 0, f"the run exited {rc}\n{up.stdout}\n{up.stderr}"
    finally:
        up.cleanup()
    log = (run_dir / "logs" / "learner.log").read_text()
    done = ast.literal_eval(re.findall(r"learner learner done: (\{.*\}); inbox", log)[-1])
    state = read_json(run_dir / "learner" / "checkpoint" / "state.json")
    q = _q_on_a0(run_dir, task)
    stored = state["actors"].get("x9", {}).get("ingested", 0) // 8
    refused = done["rejected"].get("values", 0)
    # before: 24 of 24 forged batches stored, 0 refused, |Q| on a0's states 2.09e4 (now 19.6)
    assert stored == 0 and refused == FORGED, (f"{stored} of {FORGED} forged batches stored, {refused} refused; "
                                                f"|Q| on a0's states {q:.4g} (Q_max {Q_MAX:.4g})", done)
    assert q < Q_MAX, f"|Q| on a0's states {q:.4g} > Q_max {Q_MAX:.4g}"
    assert task.reward_bound == pytest.approx(R_MAX) and task.obs_bound == 2.0
    assert "actor x9 batch 0: reward[0] = 999074 is outside [-293.728, 293.728]" in log
    assert done["rollbacks"] == 0 and done["q_rollbacks"] == 0 and done["q_largest"] < Q_MAX, done
    bounds = read_json(run_dir / "config.json")["runtime"]["task_bounds"]
    assert bounds == {"reward_bound": 220.0, "obs_bound": 2.0, "rule": "stated by the task",
                      "learner_reward_bound": pytest.approx(R_MAX)}
    acct = provenance_check(run_dir)
    assert acct["lost"] == 0 and acct["duplicated"] == 0 and acct["produced"] > 0, acct
