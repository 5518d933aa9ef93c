"""A camera task through the learner's and the actor's real parts (issue 37, points 3-4): the actor stream packs
Dict observations into frames (row 0's always sent), the wire carries them, the learner's TQC is built with DrQ's
image policy and a FrameReplayBuffer and stores each frame once (row 0 deduplicated against the stream's pin), the
journal record keeps the frames, drop_bad_rows moves the frame ids and recounts, and the actor's policy built on
the Dict space takes the learner's weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery.outbox import Outbox
from khgrl.common.delivery.stream import TransitionStream
from khgrl.common.tasks.env_descriptor import descriptor
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.common.tasks.spaces import observation_space
from khgrl.common.wire.base import Dims
from khgrl.common.wire.checks import RejectCounter
from khgrl.common.wire.protocol import Transitions, decode
from khgrl.deploy.examples.camera_task import make_task
from khgrl.learner.frame_replay import FrameReplayBuffer
from khgrl.learner.image_policy import DrQTQCPolicy
from khgrl.learner.journal_record import decode_body, encode_record
from khgrl.learner.sound import drop_bad_rows
from khgrl.learner.tqc import TQCAlgorithm

SETTINGS = TQCSettings(learning_starts=8, buffer_size=300, net_arch=(64, 64), batch_size=16, gradient_steps=2,
                       device="cpu")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The camera task's env, its descriptor and two episodes of a real actor stream's batches (decoded)."""
    torch.set_num_threads(1)
    env = KGRLEnv(make_task(), seed=0)
    task = descriptor(env)
    sent: list[bytes] = []
    outbox = Outbox(64, tmp_path_factory.mktemp("outbox"))
    stream = TransitionStream("a0", "s1", outbox, sent.append, RejectCounter("actor"), task=task.digest)
    steps, rng = 0, np.random.default_rng(0)
    for episode in range(2):
        obs, _ = env.reset(seed=episode)
        done = False
        while not done and steps < 60 * (episode + 1):
            nxt, reward, term, trunc, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            done = term or trunc or steps == 60 * (episode + 1) - 1
            stream.add(obs, nxt, info["action"], reward, term, trunc or done, False, False)
            steps += 1
            if done or stream.count % 16 == 0:
                stream.cut()
            obs = nxt
    batches = [decode(Transitions, p, Dims.of_task(task)) for p in sent]
    yield env, task, batches
    env.close()


def _store(algo, batches) -> None:
    for b in batches:
        term, trunc = b.terminated.astype(bool), b.truncated.astype(bool)
        algo.store(b.obs, b.next_obs, b.action, b.reward, (term | trunc).astype(np.float32),
                   (trunc & ~term).astype(np.float32), intervened=b.intervened, clipped=b.clipped, actor=0,
                   first_step=b.first_step, frames=b.frames, obs_frame=b.obs_frame, next_frame=b.next_frame)


def test_actor_batches_carry_each_frame_once_plus_row_0(run) -> None:
    _, task, batches = run
    assert task.cameras == {"cam": (16, 16, 3)} and [b.n for b in batches] == [16, 16, 16, 12, 4, 16, 16, 16, 8]
    for b in batches:
        assert b.obs.shape[1] == task.obs_dim and b.obs_frame[0] == 0  # row 0's frame sent, never PREV
        assert len(b.frames["cam"]) == b.n + 1  # one frame a row and row 0's observation
        assert np.array_equal(b.frames["cam"][b.obs_frame[1:]], b.frames["cam"][b.next_frame[:-1]])


def test_learner_stores_each_frame_once_and_trains(run, tmp_path) -> None:
    env, task, batches = run
    algo = TQCAlgorithm.build(task, SETTINGS, seed=0, device="cpu")
    rb = algo.buffer
    assert isinstance(rb, FrameReplayBuffer) and isinstance(algo.model.policy, DrQTQCPolicy)
    assert algo.model.policy.actor.features_extractor.features_dim == 50 + task.obs_dim
    _store(algo, batches)
    assert rb.pos == 120 and rb.store.live == 120 + 2  # one frame a step and one an episode: row 0's deduplicated
    stored = rb.store.get(rb.obs_frame[:3])["cam"]  # channel-first, as SB3 holds the model's images
    assert stored.shape == (3, 3, 16, 16)
    assert np.array_equal(stored.transpose(0, 2, 3, 1), batches[0].frames["cam"][batches[0].obs_frame[:3]])
    before = [p.detach().clone() for p in algo.model.critic.parameters()]
    algo.set_logger(tmp_path, ("csv",))
    algo.train(2, timestep=120, sample_limit=None)
    assert any(not torch.equal(a, b) for a, b in zip(before, algo.model.critic.parameters()))
    weights = algo.policy_weights()
    size = sum(w.nbytes for w in weights.values())
    assert 50_000 < size < 400_000, size  # the actor with its encoder: small for 16 x 16 images
    actor = TQCAlgorithm.actor_policy(env.observation_space, env.action_space, SETTINGS)
    assert actor.weights_template() == {k: v.shape for k, v in weights.items()}
    actor.load_weights({k: torch.from_numpy(v) for k, v in weights.items()})
    obs, _ = env.reset(seed=3)
    action, _ = actor.predict(obs, deterministic=True)
    algo.model.policy.set_training_mode(False)
    space_obs = {k: v.transpose(2, 0, 1) if v.ndim == 3 else v for k, v in obs.items()}
    expected, _ = algo.model.policy.predict(space_obs, deterministic=True)
    np.testing.assert_allclose(action, expected, rtol=1e-5, atol=1e-6)
    assert observation_space(task) == env.observation_space


def test_journal_record_keeps_the_frames(run) -> None:
    _, _, batches = run
    b = batches[2]
    rec = encode_record(b, 2)
    back, skipped = decode_body(memoryview(rec)[12:])
    assert skipped == 0 and back.n == b.n
    assert np.array_equal(back.frames["cam"], b.frames["cam"]) and np.array_equal(back.obs_frame, b.obs_frame)
    assert np.array_equal(back.next_frame, b.next_frame) and np.array_equal(back.obs, b.obs)


def test_drop_bad_rows_moves_frame_ids_and_recounts(run) -> None:
    _, task, batches = run
    algo = TQCAlgorithm.build(task, SETTINGS, seed=0, device="cpu")
    _store(algo, batches)
    rb = algo.buffer
    rb.rewards[5, 0] = np.nan
    rb.observations[70, 0, 0] = np.inf
    kept = {k: rb.store.get(rb.next_frame[[i for i in range(120) if i not in (5, 70)]])["cam"] for k in ("cam",)}
    assert drop_bad_rows(rb, task) == {0: 2}
    assert rb.pos == 118 and np.all(rb.next_frame[118:] == -1) and np.all(rb.obs_frame[118:] == -1)
    assert np.array_equal(rb.store.get(rb.next_frame[:118])["cam"], kept["cam"])
    # the dropped rows share their frames with the kept rows before and after them: none freed
    assert rb.store.live == 120 + 2 and rb.store.refs.sum() == 2 * 118  # (their frames are kept rows' too)
