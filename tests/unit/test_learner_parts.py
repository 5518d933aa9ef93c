"""The learner's parts without Zenoh: stream ordering (common/delivery/ingest.py), the replay buffer with per-slot
flags and provenance (learner/replay.py), checkpoints (learner/checkpoint.py) and the main loop
(learner/loop.py) driven with messages, collecting what it publishes. The process itself (learner/main.py)
is run for what needs no router: its command-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery.ingest import StreamTable
from khgrl.common.delivery.transport import Inbox
from khgrl.common.process import StopFlag
from khgrl.common.wire.messages import LearnerInfo
from khgrl.common.wire.protocol import Ack, Control, Keys, Status, Transitions, Weights, decode, encode
from khgrl.learner.checkpoint import (
    CheckpointError,
    checkpoint_dir,
    find_checkpoint,
    load_checkpoint_arrays,
    save_checkpoint,
)
from khgrl.learner.loop import LearnerLoop, open_learner
from khgrl.learner.replay import SIDE_ARRAYS, StreamReplayBuffer

REPO = Path(__file__).resolve().parents[2]
SMALL = TQCSettings(learning_starts=16, buffer_size=1000, net_arch=(32, 32), batch_size=32)
RUN = Keys("unit")


def batch(seq: int, first: int, n: int, actor: str = "a0", base: int = 0, stream: str = "s0", seed: int = 0,
          intervened: int = 1) -> Transitions:
    """A decoded transitions message, as the learner receives it."""
    rng = np.random.default_rng(seed + 1000 * seq)
    obs = rng.uniform(0, 1, (n, 5)).astype(np.float32)
    msg = Transitions(actor=actor, first_step=first, obs=obs, next_obs=obs[::-1].copy(),
                      action=rng.uniform(-1, 1, (n, 2)).astype(np.float32), reward=np.ones(n, np.float32),
                      terminated=np.zeros(n, np.uint8), truncated=np.zeros(n, np.uint8),
                      intervened=np.full(n, intervened, np.uint8), clipped=np.zeros(n, np.uint8), base_seq=base,
                      stream=stream, task="0123456789abcdef")
    return decode(Transitions, encode(msg, actor, seq))


class Collect:
    """A publisher that keeps what the loop publishes (each message also encoded, as Zenoh would send it)."""

    def __init__(self) -> None:
        self.queries = 0
        self.sent: list = []

    def _keep(self, msg) -> None:
        encode(msg, "learner", len(self.sent))
        self.sent.append(msg)

    weights = ack = status = _keep

    def of(self, cls) -> list:
        return [m for m in self.sent if isinstance(m, cls)]


def make_loop(tmp_path: Path, *, resume: bool = False, checkpoint_every: int = 0, tqc: TQCSettings = SMALL):
    trainer, streams = open_learner(tqc, 1, tmp_path / "learner", resume=resume, logger_formats=("csv",))
    pub = Collect()
    loop = LearnerLoop(trainer, streams, pub, learner_id="learner", learner_dir=tmp_path / "learner",
                       checkpoint_every=checkpoint_every, flag=StopFlag())
    return loop, pub


# ------------------------------------------------------------------------------------ ingest
def test_stream_order_accepts_holds_and_detects_duplicates():
    table = StreamTable()
    assert table.offer(batch(1, 8, 8)).result == "held"
    assert table.offer(batch(2, 16, 8)).result == "held"
    assert table["a0"].next_seq == 0 and table["a0"].held == 2
    res = table.offer(batch(0, 0, 8))
    assert res.result == "accepted" and [m.envelope.seq for m in res.ready] == [0, 1, 2]
    assert table["a0"].next_seq == 3 and not table["a0"].pending
    dup = table.offer(batch(1, 8, 8))
    assert dup.result == "duplicate" and dup.ready == [] and table["a0"].duplicates == 1
    assert table.offer(batch(3, 24, 8)).result == "accepted"


def test_stream_restart_and_base_seq():
    table = StreamTable()
    table.offer(batch(0, 0, 8))
    # the same actor with a new stream id: a new stream (a new provenance code), starting at its base_seq
    res = table.offer(batch(0, 0, 4, stream="s1"))
    assert res.result == "accepted" and res.stream.code == 1
    assert table.codes == [{"actor": "a0", "stream": "s0"}, {"actor": "a0", "stream": "s1"}]
    # a stream adopted mid-way: the actor holds nothing before seq 6
    res = table.offer(batch(6, 40, 8, actor="a1", base=6, stream="t0"))
    assert res.result == "accepted" and table["a1"].next_seq == 7 and table["a1"].skipped == 0
    # an actor that dropped batches 8..9 (durable in an earlier learner's checkpoint): skipped, not waited for
    assert table.offer(batch(11, 80, 8, actor="a1", stream="t0")).result == "held"
    assert table.offer(batch(12, 88, 8, actor="a1", base=10, stream="t0")).result == "held"
    assert table["a1"].skipped == 3 and table["a1"].next_seq == 10  # 7, 8, 9: not waited for
    res = table.offer(batch(10, 72, 8, actor="a1", base=10, stream="t0"))
    assert res.result == "accepted" and [m.envelope.seq for m in res.ready] == [10, 11, 12]


def test_stream_table_state_round_trip():
    table = StreamTable()
    for seq in range(3):
        table.offer(batch(seq, 8 * seq, 8))
    st = table.state()
    assert st["actors"]["a0"]["durable"] == 2 and table["a0"].durable == -1  # durable once the file is written
    table.mark_durable()
    again = StreamTable.from_state(json.loads(json.dumps(st)))
    assert again.codes == table.codes and again["a0"].next_seq == 3 and again["a0"].durable == 2


# ------------------------------------------------------------------------------------ replay buffer
def test_replay_buffer_side_arrays_follow_the_slots():
    from khgrl.common.tasks.spaces import action_space, observation_space

    rb = StreamReplayBuffer(4, observation_space(), action_space(), device="cpu")
    for i in range(6):  # wraps: slots 0 and 1 are overwritten by transitions 4 and 5
        obs = np.full((1, 5), i / 10, np.float32)
        rb.add(obs, obs, np.zeros((1, 2), np.float32), np.array([i], np.float32), np.array([0.0], np.float32),
               [{"TimeLimit.truncated": False}], intervened=i % 2, clipped=int(i == 5), actor=7, step=100 + i)
    assert rb.full and rb.pos == 2 and rb.size() == 4
    assert rb.provenance_step.tolist() == [104, 105, 102, 103]
    assert rb.rewards[:, 0].tolist() == [4, 5, 2, 3]
    assert rb.intervened.tolist() == [0, 1, 0, 1] and rb.clipped.tolist() == [0, 1, 0, 0]
    assert set(rb.side_arrays()) == set(SIDE_ARRAYS)
    with pytest.raises(ValueError, match="n_envs"):
        StreamReplayBuffer(4, observation_space(), action_space(), device="cpu", n_envs=2)


def test_replay_buffer_class_changes_no_random_draw():
    """TQC with our buffer class is seeded exactly as with SB3's own buffer (same initial networks)."""
    from khgrl.common.tasks.spaces import SpacesEnv
    from khgrl.learner.trainer import build_model
    from sb3_contrib import TQC

    ours = build_model(SMALL, 1)
    plain = TQC("MlpPolicy", SpacesEnv(), **SMALL.sb3_kwargs(1))
    assert isinstance(ours.replay_buffer, StreamReplayBuffer)
    for mine, theirs in ((ours.policy.actor, plain.policy.actor), (ours.policy.critic, plain.policy.critic)):
        a, b = mine.state_dict(), theirs.state_dict()
        assert a.keys() == b.keys() and all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)


def test_replay_buffer_save_load_keeps_side_arrays(tmp_path):
    loop, _ = make_loop(tmp_path)
    loop.offer(batch(0, 0, 8))
    loop.offer(batch(1, 8, 8, intervened=0))
    model = loop.trainer.algo.model
    model.save_replay_buffer(tmp_path / "rb.pkl")
    before = {k: v.copy() for k, v in model.replay_buffer.side_arrays().items()}
    model.replay_buffer = None
    model.load_replay_buffer(tmp_path / "rb.pkl")
    rb = model.replay_buffer
    assert isinstance(rb, StreamReplayBuffer) and rb.pos == 16
    for name, arr in rb.side_arrays().items():
        np.testing.assert_array_equal(arr, before[name])
    assert rb.intervened[:16].tolist() == [1] * 8 + [0] * 8 and rb.provenance_step[:17].tolist() == [*range(16), -1]


# ------------------------------------------------------------------------------------ checkpoint
def test_checkpoint_round_trip(tmp_path):
    loop, _ = make_loop(tmp_path)
    for seq in range(4):
        loop.offer(batch(seq, 8 * seq, 8))
    assert loop.train() and loop.trainer.version == 1
    path = loop.checkpoint()
    assert path == checkpoint_dir(tmp_path / "learner") == find_checkpoint(tmp_path / "learner")
    assert sorted(p.name for p in (tmp_path / "learner").iterdir() if p.name.startswith("checkpoint")) == ["checkpoint"]
    state = json.loads((path / "state.json").read_text())
    assert state["format"] == 2 and state["total_ingested"] == 32 and state["replay"] == {"pos": 32, "full": False,
                                                                                         "size": 1000}
    assert state["codes"] == [{"actor": "a0", "stream": "s0"}] and state["actors"]["a0"]["durable"] == 3
    arrays = load_checkpoint_arrays(path)
    assert arrays["provenance_step"][:32].tolist() == list(range(32)) and int(arrays["intervened"].sum()) == 32
    assert np.all(arrays["provenance_actor"][32:] == -1)

    again, _ = make_loop(tmp_path, resume=True)
    tr = again.trainer
    assert (tr.total, tr.version, tr.iterations, tr.gradient_steps) == (32, 1, 1, SMALL.gradient_steps)
    assert [at for at, _ in tr.due] == [at for at, _ in loop.trainer.due] == [32]
    assert tr.epoch != loop.trainer.epoch and again.streams["a0"].durable == 3
    np.testing.assert_array_equal(tr.buffer.observations, loop.trainer.buffer.observations)
    for name, arr in tr.buffer.side_arrays().items():
        np.testing.assert_array_equal(arr, loop.trainer.buffer.side_arrays()[name])
    w0, w1 = loop.trainer.weights().tensors, tr.weights().tensors
    assert all(np.array_equal(w0[k], w1[k]) for k in w0)


def test_checkpoint_missing_or_old(tmp_path):
    learner_dir = tmp_path / "learner"
    assert find_checkpoint(learner_dir) is None
    with pytest.raises(CheckpointError, match="no checkpoint"):
        open_learner(SMALL, 1, learner_dir, resume=True)
    # a crash between the two renames leaves checkpoint.old: found
    old = learner_dir / "checkpoint.old"
    old.mkdir(parents=True)
    (old / "state.json").write_text(json.dumps({"format": 1}))
    assert find_checkpoint(learner_dir) == old
    with pytest.raises(CheckpointError, match="format 1"):
        open_learner(SMALL, 1, learner_dir, resume=True)


def test_save_checkpoint_replaces_the_previous_one(tmp_path):
    loop, _ = make_loop(tmp_path)
    loop.offer(batch(0, 0, 8))
    first = save_checkpoint(tmp_path / "learner", loop.trainer.algo, {"mark": 1})
    second = save_checkpoint(tmp_path / "learner", loop.trainer.algo, {"mark": 2})
    assert first == second and json.loads((second / "state.json").read_text())["mark"] == 2
    assert not (tmp_path / "learner" / "checkpoint.old").exists()


# ------------------------------------------------------------------------------------ the loop, without Zenoh
def test_loop_orders_stream_and_keeps_sb3_schedule(tmp_path):
    loop, pub = make_loop(tmp_path)
    tr = loop.trainer
    ack = lambda: tr.ack(loop.streams["a0"])  # noqa: E731
    assert loop.offer(batch(1, 8, 8)) == "held"  # gap: held until seq 0 arrives
    assert tr.total == 0 and ack().received == -1
    assert loop.offer(batch(0, 0, 8)) == "accepted"
    assert tr.total == 16 and ack().received == 1
    assert loop.offer(batch(0, 0, 8)) == "duplicate" and tr.total == 16
    # inside learning_starts: no training due, trained = everything ingested, down to a multiple of train_freq
    assert not tr.due and ack().trained == 16
    assert loop.offer(batch(2, 16, 5)) == "accepted" and not tr.due  # 21: the next multiple of 8 is 24
    # past learning_starts, before the first iteration is due (24): still down to the grid, so that the actor
    # (21 - 16 < max_lead) steps on to 24 instead of waiting for weights while the learner waits for its 24th
    assert tr.first_due == 24 and ack().trained == 16
    assert loop.offer(batch(3, 21, 8)) == "accepted"  # 29 ingested: due at 24
    assert [at for at, _ in tr.due] == [24]
    assert ack().trained == 0  # the iteration at 24 is due, not done: the initial weights cover nothing
    loop.step()
    assert not tr.due and tr.version == 1 and tr.gradient_steps == SMALL.gradient_steps and tr.iterations == 1
    weights = pub.of(Weights)
    assert [w.version for w in weights] == [1] and weights[0].trained == {"a0": 24}
    acks = pub.of(Ack)
    assert acks[-1].trained == 24 and acks[-1].version == 1 and acks[-1].received == 3 and acks[-1].stream == "s0"
    assert all(a.epoch == tr.epoch for a in acks) and weights[0].epoch == tr.epoch
    assert int(tr.buffer.intervened[:29].sum()) == 29
    loop.step()  # nothing new: no ack, no training
    assert len(pub.of(Ack)) == len(acks)


@pytest.mark.parametrize("learning_starts, lengths", [
    (16, [7, 13, 4, 9, 30, 11]),  # 20 after the second episode: between learning_starts and the first due (24)
    (21, [10, 12, 50]),  # 22, 23: inside (21, 24)
    (100, [43, 60, 43, 43]),  # panda:pick-pixels' first grid run: 103 in, the first iteration due at 104
    (16, [8, 8, 8, 5, 3, 17]),  # ends on the grid
])
def test_flow_control_never_waits_for_an_iteration_that_cannot_come(tmp_path, learning_starts: int,
                                                                   lengths: list[int]) -> None:
    """One actor with the actor's rule (``common/delivery/actor_side.py``: wait while ``sent - ack.trained >=
    max_lead``; a batch cut at multiples of its running index or at an episode's end) against the real loop:
    whenever the actor waits, a training iteration is due, whatever the episodes' lengths."""
    tqc = TQCSettings(learning_starts=learning_starts, buffer_size=1000, net_arch=(8, 8), batch_size=8,
                      gradient_steps=1)
    loop, _ = make_loop(tmp_path, tqc=tqc)
    tr, max_lead, cut = loop.trainer, 8, 8
    sent = pending = seq = waits = 0
    trained = lambda: tr.ack(loop.streams["a0"]).trained if "a0" in loop.streams else 0  # noqa: E731
    for length in lengths:
        for t in range(length):
            while sent - trained() >= max_lead:
                assert tr.due, f"deadlock: the actor waits at {sent} and no iteration is due ({tr.total} in)"
                loop.step()
                waits += 1
            pending += 1
            if (sent + pending) % cut == 0 or t == length - 1:
                assert loop.offer(batch(seq, sent, pending)) == "accepted"
                seq, sent, pending = seq + 1, sent + pending, 0
    assert waits > 0 and tr.iterations > 0


def test_loop_receives_payloads_and_rejects_bad_ones(tmp_path):
    loop, pub = make_loop(tmp_path)
    good = encode(batch(0, 0, 8), "a0", 0)
    loop.receive("transitions", RUN.transitions("a0"), good)
    loop.receive("transitions", RUN.transitions("a1"), good)  # a0's batch on a1's key
    loop.receive("transitions", RUN.transitions("a0"), b"\x00garbage")
    loop.receive("control", RUN.control("learner"), encode(Ack(actor="a0", received=0, durable=0, trained=0,
                                                               version=0, epoch="e"), "x", 0))
    assert loop.trainer.total == 8 and loop.rejects.by_kind() == {"transitions": 2, "control": 1}
    loop.step()
    assert [a.actor for a in pub.of(Ack)] == ["a0"]
    info = loop.info()
    assert isinstance(info, LearnerInfo) and info.ingested == 8 and info.next_seq == {"a0": 1}
    assert info.rejects == {"transitions": 2, "control": 1} and info.durable == {"a0": -1}
    decode(Status, encode(Status(role="learner", info=info), "learner", 0))


def test_loop_controls_and_checkpoint_interval(tmp_path):
    loop, pub = make_loop(tmp_path, checkpoint_every=16)
    loop.control(Control(command="pause"))
    for seq in range(4):
        loop.offer(batch(seq, 8 * seq, 8))
    loop.step()
    assert loop.paused and loop.trainer.due and loop.trainer.version == 0  # paused: no training
    assert loop.durable.checkpoints == 1 and pub.of(Ack)[-1].durable == 3  # 32 >= 16 ingested since the start
    loop.control(Control(command="resume"))
    loop.step()
    assert loop.trainer.version == 1 and loop.durable.checkpoints == 1
    loop.control(Control(command="checkpoint"))
    loop.step()
    assert loop.durable.checkpoints == 2
    loop.control(Control(command="stop"))
    assert loop.flag and loop.flag.reason == "stop command"


def test_loop_run_drains_an_inbox_until_stopped(tmp_path):
    loop, pub = make_loop(tmp_path)
    loop.start()
    assert [w.version for w in pub.of(Weights)] == [0]
    inbox = Inbox(maxsize=100, overflow="drop_newest")
    for seq in range(3):
        inbox.put(("transitions", RUN.transitions("a0"), encode(batch(seq, 8 * seq, 8), "a0", seq), 0.0))
    inbox.put(("control", RUN.control("learner"), encode(Control(command="stop"), "launcher", 0), 0.0))
    loop.run(inbox)
    assert loop.flag.reason == "stop command" and loop.trainer.total == 24 and inbox.qsize() == 0
    assert pub.of(Ack)[-1].received == 2
    loop.checkpoint()
    assert pub.of(Ack)[-1].durable == 2 and loop.summary()["offers"] == {"accepted": 3}


def test_loop_status_rate(tmp_path):
    now = [0.0]
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    pub = Collect()
    loop = LearnerLoop(trainer, streams, pub, learner_id="L1", learner_dir=tmp_path / "learner", checkpoint_every=0,
                       flag=StopFlag(), clock=lambda: now[0])
    for seq in range(4):
        loop.offer(batch(seq, 8 * seq, 8))
    now[0] = 2.0
    loop.step()  # trains one iteration, then status: 8 gradient steps in 2 s
    (status,) = pub.of(Status)
    assert status.info.id == "L1" and status.info.grad_steps_per_s == SMALL.gradient_steps / 2
    assert status.info.pending_iterations == 1 and status.info.version == 1  # due at 24 and 32: one left


# ------------------------------------------------------------------------------------ the process
def _learner(*args: str) -> subprocess.CompletedProcess:
    code = "from khgrl.learner.main import main; import sys; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], cwd=REPO, capture_output=True, text=True, timeout=120)


def test_resume_without_checkpoint_is_an_error(tmp_path):
    res = _learner("--run", "r1", "--connect", "tcp/127.0.0.1:1", "--run-dir", str(tmp_path), "--resume")
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "--resume: no checkpoint" in lines[0] and str(tmp_path) in lines[0]
    assert not (tmp_path / "learner" / "learner.log").exists()


def test_bad_settings_are_an_error(tmp_path):
    res = _learner("--run", "bad/run", "--run-dir", str(tmp_path))
    assert res.returncode == 2 and "run id" in res.stderr
    res = _learner("--config", str(tmp_path / "missing.json"))
    assert res.returncode == 2 and "does not exist" in res.stderr


def test_help_lists_the_learner_settings_with_defaults():
    from khgrl.learner.main import build_parser

    text = build_parser().format_help()
    for flag in ("--learning-starts", "--checkpoint-every", "--learner-threads", "--learner-nice", "--buffer-size",
                 "--config", "--resume", "--id"):
        assert flag in text
    assert "--scenario" not in text and "(default: 100)" in text
