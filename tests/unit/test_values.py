"""Issue 21, "values are bounded": the task descriptor's value bounds, the learner's check of arriving batches
(:func:`check_bounds`, counted as ``values`` rejects), the required task digest, the rollback of a training iteration
that went non-finite, and the checks a resumed learner makes of its checkpoint."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import TQCSettings
from khgrl.common.process import StopFlag
from khgrl.common.tasks.api import TaskError
from khgrl.common.tasks.checks import value_bounds
from khgrl.common.tasks.passage.env import PassageEnv
from khgrl.common.wire.bounds import bad_rows, check_bounds
from khgrl.common.wire.checks import ProtocolError
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import TaskInfo, Transitions
from khgrl.common.wire.protocol import Keys, decode, encode
from khgrl.learner.checkpoint import MODEL_FILE, CheckpointError, find_checkpoint
from khgrl.learner.loop import LearnerLoop, open_learner

SMALL = TQCSettings(learning_starts=16, buffer_size=1000, net_arch=(32, 32), batch_size=32)
KEYS = Keys("unit")


@pytest.fixture(scope="module")
def task() -> TaskDescriptor:
    return PassageEnv("low_cov").descriptor("passage:low_cov")


def _batch(desc: TaskDescriptor | None, seq: int = 0, n: int = 8, actor: str = "a0", **over) -> Transitions:
    rng = np.random.default_rng(seq)
    obs = rng.uniform(0, 1, (n, 5)).astype(np.float32)
    fields = dict(actor=actor, first_step=n * seq, obs=obs, next_obs=obs[::-1].copy(),
                  action=rng.uniform(-1, 1, (n, 2)).astype(np.float32), reward=rng.normal(size=n).astype(np.float32),
                  terminated=np.zeros(n, np.uint8), truncated=np.zeros(n, np.uint8), intervened=np.zeros(n, np.uint8),
                  clipped=np.zeros(n, np.uint8), base_seq=0, stream="s0",
                  task=desc.digest if desc is not None else "0123456789abcdef")
    fields.update(over)
    return Transitions(**fields)


def without_digest(payload: bytes) -> bytes:
    """A batch's payload without its ``task`` field (``encode`` refuses to make one)."""
    import msgpack

    m = msgpack.unpackb(payload, raw=False)
    del m["task"]
    return msgpack.packb(m, use_bin_type=True)


class _Pub:
    queries = 0

    def __init__(self) -> None:
        self.sent: list = []

    def _keep(self, msg) -> None:
        self.sent.append(msg)

    weights = ack = status = _keep


def _loop(tmp_path: Path, task, *, resume: bool = False, algo: str = "tqc") -> LearnerLoop:
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=resume, logger_formats=("csv",),
                                    task=task, algo=algo)
    loop = LearnerLoop(trainer, streams, _Pub(), learner_id="learner", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag())
    if task is not None:
        loop.set_task(task)
    return loop


# ------------------------------------------------------------------------------------ the descriptor's bounds
def test_the_descriptor_carries_value_bounds_that_survive_the_wire(task):
    # passage world: |r| <= 200 (goal) + 10 + 10 (obstacle, wall), stated by the task, plus the largest action cost
    # 4 x 10 x |0.96, 0.96|^2 = 73.7 (before issue 34 point 5: the default 1e6 plus it, 1,000,073)
    assert task.reward_bound == pytest.approx(293.728) and task.obs_bound == 2.0
    low, high = task.obs_limits
    assert np.allclose(low, [-0.101] * 3 + [-1.201] * 2) and np.allclose(high, [1.101] * 3 + [1.201] * 2)
    back = decode(TaskInfo, encode(TaskInfo(sender_id="a0", descriptor=task), "a0", 0)).descriptor
    assert (back.reward_bound, back.obs_bound, back.digest) == (task.reward_bound, task.obs_bound, task.digest)
    assert dataclasses.replace(task, reward_bound=10.0).digest != task.digest  # learner and actor agree on it
    wire = task.to_wire()
    for bad in (0.0, -1.0, float("inf"), 1e13, True, "1e6", None):
        with pytest.raises(ProtocolError, match="reward_bound"):
            TaskDescriptor.from_wire({**wire, "reward_bound": bad})


def test_a_task_declares_its_bounds_and_bad_declarations_are_one_error():
    from khgrl.deploy.examples.own_task import make_task

    t = dataclasses.replace(make_task(), reward_bound=1e6, obs_bound=1e6)
    box, space = ((0.0,) * 3, (1.0,) * 3), (np.full(7, -np.inf), np.full(7, np.inf))
    reward, obs = value_bounds(t, box, space)
    assert reward == pytest.approx(1e6 + 4 * t.action_cost * 3) and obs == 1e6
    assert value_bounds(dataclasses.replace(t, reward_bound=5.0, obs_bound=2.0), box, space) == (
        pytest.approx(5.0 + 4 * t.action_cost * 3), 2.0)
    for field, v in (("reward_bound", 0), ("reward_bound", float("nan")), ("obs_bound", 1e10), ("obs_bound", "x"),
                     ("obs_bound", None)):
        with pytest.raises(TaskError, match=field):
            value_bounds(dataclasses.replace(t, **{field: v}), box, space)
    with pytest.raises(TaskError, match="obs_bound"):  # a space that lies wholly beyond the bound
        value_bounds(t, box, (np.full(7, 2e6), np.full(7, 3e6)))


# ------------------------------------------------------------------------------------ derived bounds
def test_a_derived_bound_is_four_times_what_was_seen_rounded_up_to_a_power_of_two():
    from khgrl.common.tasks.derived_bounds import margin_bound

    assert [margin_bound(v) for v in (10.0, 10.2, 16.0, 200.0, 0.3, 0.1, 0.0)] == [64, 64, 64, 1024, 2, 1, 1]


def test_a_task_that_states_no_bounds_gets_them_from_its_environment(monkeypatch):
    """The example task (``deploy/examples/own_task.py``: +200 at the goal, -10 blocked; positions in the unit cube)
    states no bounds: replaying its demonstrations (which reach the goal) and 2 random episodes shows |r| 200 and
    |obs| 0.87, so its bounds are 1024 and 4 (before issue 34 point 5: 1e6 and 1e6). The derivation is the same in
    every process (a digest the launcher, actors and learner agree on), runs once per environment, and the run's
    config says how the bounds came about."""
    from khgrl.common.tasks import derived_bounds
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.env_descriptor import task_bounds
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    task = load_task("khgrl.deploy.examples.own_task:make_task")
    assert task.reward_bound is None and task.obs_bound is None
    calls = []
    seen = derived_bounds.seen_ranges
    monkeypatch.setattr(derived_bounds, "seen_ranges", lambda *a: calls.append(1) or seen(*a))
    env = KGRLEnv(task, seed=7)
    desc = env.descriptor("own")
    assert desc.reward_bound == pytest.approx(1024 + 4 * 10.0 * (0.96 ** 2 * 2 + 0.78 ** 2)) and desc.obs_bound == 4.0
    assert env.descriptor("own").digest == desc.digest and len(calls) == 1  # derived once per environment
    assert KGRLEnv(task, seed=8).descriptor("own").digest == desc.digest  # another actor: the same bounds
    record = task_bounds(env)[1]
    assert record["derived"] == ["reward_bound", "obs_bound"] and record["seen"]["reward"] == 200.0
    assert record["rule"].startswith("4 x the largest |value| seen replaying the demonstrations and 2 random")
    stated = dataclasses.replace(task, reward_bound=300.0)  # a bound the task states is kept
    assert derived_bounds.resolve_bounds(stated, env.world.demos, env.world.low, env.world.high)[0].reward_bound == 300


def test_an_environment_that_fails_while_its_bounds_are_derived_is_one_task_error():
    from khgrl.common.tasks.derived_bounds import resolve_bounds
    from khgrl.deploy.examples.own_task import make_task

    class Broken:
        def reset(self, seed=None):
            raise RuntimeError("no robot")

    task = dataclasses.replace(make_task(), make_env=lambda seed: Broken())
    with pytest.raises(TaskError, match="deriving its value bounds .* RuntimeError: no robot"):
        resolve_bounds(task, np.zeros((2, 10, 3)), np.zeros(3), np.ones(3))


# ------------------------------------------------------------------------------------ check_bounds, bad_rows
def test_check_bounds_refuses_what_overflows_and_names_it(task):
    assert check_bounds(_batch(task), task) is None
    edge = _batch(task, obs=np.full((8, 5), 1.05, np.float32))  # an environment rounding at its space's edge
    assert check_bounds(edge, task) is None
    r = np.zeros(8, np.float32)
    r[3] = 3e38
    why = check_bounds(_batch(task, reward=r), task)
    assert why.startswith("reward[3] = 3e+38 is outside [-293.728, 293.728]")
    old = r.copy()
    old[3] = 0.999 * 1_000_073  # within the old default bound (issue 34 point 5), 3,400 times the passage world's
    assert check_bounds(_batch(task, reward=old), task).startswith("reward[3] = 999073 is outside")
    obs = np.zeros((8, 5), np.float32)
    obs[[2, 5], 1] = -3e38
    why = check_bounds(_batch(task, next_obs=obs), task)
    assert why.startswith("next_obs[2, 1] = -3e+38 is outside [-0.101, 1.101]") and "(2 of 8 rows" in why
    obs[2, 1] = np.nan  # (the wire refuses NaN; a stored row is checked with the same function)
    assert "next_obs[2, 1] is not finite" in check_bounds(_batch(task, next_obs=obs), task)
    assert check_bounds(_batch(task, obs=np.full((8, 5), 2.0, np.float32)), task).startswith("obs[0, 0] = 2")
    # a dimension the space leaves unbounded is still held to +-obs_bound
    open_task = dataclasses.replace(task, obs_low=(-1e30,) * 5, obs_high=(1e30,) * 5)
    assert check_bounds(_batch(open_task, obs=np.full((8, 5), 1.9, np.float32)), open_task) is None
    far = _batch(open_task, obs=np.full((8, 5), 3e38, np.float32))
    assert "outside [-2.401, 2.401]" in check_bounds(far, open_task)  # (obs_bound 2, widened by a tenth of 4)
    # without a task: finite and within +-1e12
    assert check_bounds(_batch(None, reward=np.full(8, 1e9, np.float32)), None) is None
    assert check_bounds(_batch(None, reward=r), None) is not None


def test_bad_rows_marks_rows_in_sb3_shapes(task):
    n = 6
    obs = np.full((n, 1, 5), 0.5, np.float32)
    reward = np.zeros((n, 1), np.float32)
    obs[1, 0, 4] = 1e20
    reward[3, 0] = -np.inf
    action = np.zeros((n, 1, 2), np.float32)
    action[5, 0, 0] = 2.0
    mask = bad_rows({"obs": obs, "next_obs": obs.copy(), "reward": reward, "action": action}, task)
    assert mask.tolist() == [False, True, False, True, False, True]
    assert bad_rows({"obs": obs, "next_obs": obs, "reward": reward}, task).tolist() == [0, 1, 0, 1, 0, 0]


# ------------------------------------------------------------------------------------ the learner refuses
def test_the_learner_refuses_out_of_bound_batches_and_batches_without_a_digest(tmp_path, task, caplog):
    loop = _loop(tmp_path, task)
    r = np.full(8, 3e38, np.float32)
    with caplog.at_level(logging.WARNING, logger="khgrl.protocol"):
        loop.receive("transitions", KEYS.transitions("x9"), encode(_batch(task, actor="x9", reward=r), "x9", 0))
        loop.receive("transitions", KEYS.transitions("x9"), without_digest(encode(_batch(task, actor="x9"), "x9", 1)))
    assert loop.rejects.by_kind() == {"values": 1, "transitions": 1}
    assert "actor x9 batch 0: reward[0] = 3e+38 is outside" in caplog.text and "task: missing" in caplog.text
    assert loop.trainer.total == 0 and "x9" not in loop.streams
    loop.receive("transitions", KEYS.transitions("a0"), encode(_batch(task), "a0", 0))
    assert loop.trainer.total == 8 and loop.info().rejects == {"values": 1, "transitions": 1}


# ------------------------------------------------------------------------------------ rollback
def _train_ready(loop: LearnerLoop, task, seqs=range(4)) -> None:
    """Batches past learning_starts stored: iterations at 24 and 32 due."""
    for seq in seqs:
        loop.offer(decode(Transitions, encode(_batch(task, seq), "a0", seq)))


def _state(algo) -> dict[str, torch.Tensor]:
    snap = algo.snapshot()
    flat = {f"policy.{k}": v for k, v in snap["policy"].items()}
    for i, opt in enumerate(snap["optimizers"]):
        for p, st in opt["state"].items():
            flat.update({f"opt{i}.{p}.{k}": v for k, v in st.items()})
    return flat


@pytest.mark.parametrize("algo", ["tqc", "sac", "sac_ln"])
def test_an_iteration_with_a_non_finite_loss_is_rolled_back(tmp_path, task, algo, caplog):
    loop = _loop(tmp_path, task, algo=algo)
    _train_ready(loop, task)
    assert loop.work() and loop.trainer.rollbacks == 0  # one good iteration: optimiser states exist
    before = _state(loop.trainer.algo)
    version = loop.trainer.version
    loop.trainer.buffer.rewards[:32, 0] = 3e38  # stored without the check (e.g. by an older learner)
    with caplog.at_level(logging.WARNING, logger="khgrl.learner"):
        while loop.trainer.rollbacks == 0 and loop.trainer.due:
            assert loop.work()
    assert loop.trainer.rollbacks >= 1 and "rolled back" in caplog.text, "the poisoned rows were never sampled"
    after = _state(loop.trainer.algo)
    assert loop.trainer.algo.fault() is None and before.keys() == after.keys()
    if loop.trainer.rollbacks == loop.trainer.iterations - 1:  # every iteration since was rolled back
        assert all(torch.equal(before[k], after[k]) for k in before)
    weights = [m for m in loop.pub.sent if hasattr(m, "tensors")][-1]
    assert weights.version > version and all(np.isfinite(v).all() for v in weights.tensors.values())
    assert loop.info().rollbacks == loop.trainer.rollbacks


@pytest.mark.parametrize("algo", ["tqc", "sac_ln"])
def test_an_iteration_that_leaves_a_nan_parameter_is_rolled_back_exactly(tmp_path, task, monkeypatch, algo):
    loop = _loop(tmp_path, task, algo=algo)
    _train_ready(loop, task)
    assert loop.work()
    model = loop.trainer.algo.model
    before = _state(loop.trainer.algo)
    train = model.train

    def poisoned(*args, **kwargs):
        train(*args, **kwargs)
        with torch.no_grad():
            next(model.critic.parameters()).view(-1)[0] = float("nan")

    monkeypatch.setattr(model, "train", poisoned)
    assert loop.work() and loop.trainer.rollbacks == 1
    after = _state(loop.trainer.algo)
    assert all(torch.equal(before[k], after[k]) for k in before), "not restored to before the iteration"
    assert loop.trainer.last_rollback.startswith("parameter critic.")
    monkeypatch.undo()
    _train_ready(loop, task, [4])
    assert loop.work() and loop.trainer.rollbacks == 1  # training goes on from the restored state
    assert not all(torch.equal(before[k], v) for k, v in _state(loop.trainer.algo).items())


def test_a_bug_in_training_is_not_taken_for_a_numerical_fault(tmp_path, task, monkeypatch):
    loop = _loop(tmp_path, task)
    _train_ready(loop, task)

    def broken(*args, **kwargs):
        raise ValueError("a bug")

    monkeypatch.setattr(loop.trainer.algo.model, "train", broken)
    with pytest.raises(ValueError, match="a bug"):
        loop.work()


# ------------------------------------------------------------------------------------ resume checks
def test_a_resumed_learner_drops_stored_rows_out_of_bounds(tmp_path, task, caplog):
    loop = _loop(tmp_path, task)
    _train_ready(loop, task)
    rb = loop.trainer.buffer
    rb.rewards[[3, 17], 0] = 3e38  # as an older learner stored them
    rb.next_observations[20, 0, 2] = np.inf
    loop.checkpoint()
    with caplog.at_level(logging.WARNING, logger="khgrl.learner"):
        again = _loop(tmp_path, task, resume=True)
    rb = again.trainer.buffer
    assert rb.pos == 29 and not rb.full and "dropped 3 of the stored transitions (by actor code: {0: 3})" in caplog.text
    assert rb.provenance_step[:29].tolist() == [s for s in range(32) if s not in (3, 17, 20)]
    assert (rb.provenance_actor[29:] == -1).all() and np.abs(rb.rewards[:29]).max() < 10
    assert again.trainer.total == 32  # what the streams and acks say is unchanged


def test_a_checkpoint_with_a_nan_parameter_is_refused_or_the_previous_one_taken(tmp_path, task):
    loop = _loop(tmp_path, task)
    _train_ready(loop, task)
    loop.checkpoint()
    ckpt = find_checkpoint(tmp_path / "learner")
    good = ckpt.parent / "good"
    import shutil

    shutil.copytree(ckpt, good)
    with torch.no_grad():
        next(loop.trainer.algo.model.actor.parameters()).view(-1)[0] = float("nan")
    loop.checkpoint()
    with pytest.raises(CheckpointError, match=f"{ckpt / MODEL_FILE}: parameter actor.* is not finite"):
        _loop(tmp_path, task, resume=True)
    good.rename(ckpt.parent / "checkpoint.old")  # a save cut short after the new one was in place
    again = _loop(tmp_path, task, resume=True)
    assert again.trainer.algo.fault() is None and again.trainer.total == 32


def test_an_actor_does_not_send_a_transition_the_learner_would_refuse(tmp_path, task, caplog):
    """A sensor glitch (a reward of 3e38, an observation far outside the space) must not stall the actor: a batch
    holding it would be refused whole and never acked. The actor leaves such a transition out, counts and logs it,
    and sends the others."""
    from khgrl.common.delivery.outbox import Outbox
    from khgrl.common.delivery.stream import TransitionStream
    from khgrl.common.wire.checks import RejectCounter

    sent: list[bytes] = []
    stream = TransitionStream("a0", "s1", Outbox(1000, tmp_path / "outbox"), sent.append, RejectCounter("a0"),
                              task=task.digest)
    stream.bounds = task
    obs = np.full(task.obs_dim, 0.5, np.float32)
    act = np.zeros(task.out_dim, np.float32)
    glitches = [(obs, 3e38), (np.full(task.obs_dim, 1e9, np.float32), 0.0), (obs, float("nan"))]
    with caplog.at_level(logging.ERROR, logger="khgrl.actor"):
        stream.add(obs, obs, act, 1.0, False, False, False, False)
        for o, r in glitches:
            stream.add(o, obs, act, r, False, False, False, False)
        stream.add(obs, obs, act, 2.0, False, False, False, False)
    stream.cut()
    assert stream.out_of_bounds == 3 and stream.summary()["out_of_bounds"] == 3
    (batch,) = [decode(Transitions, p) for p in sent]
    assert batch.reward.tolist() == [1.0, 2.0] and batch.first_step == 0 and stream.count == 2
    assert check_bounds(batch, task) is None
    assert "transition 1 not sent" in caplog.text and "3e+38" in caplog.text
