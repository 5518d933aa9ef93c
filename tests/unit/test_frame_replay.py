"""The replay for image observations that stores each camera frame once (learner/frame_replay.py, frame_store.py,
frame_batch.py; issue 37 point 3): a stream of episodes holds one frame per step plus one per episode, sampled
minibatches carry exactly the pixels stored for each row, overwritten slots (first in first out, and per-actor
share eviction) free their frames and a frame referenced is never freed, a pickled (checkpointed) buffer comes
back the same and goes on with the stream."""

from __future__ import annotations

import copy
import json
import tempfile
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces
from khgrl.learner.checkpoint import copy_buffer
from khgrl.learner.frame_batch import PREV, pack_frames
from khgrl.learner.frame_replay import FrameReplayBuffer, frame_capacity
from khgrl.learner.frame_store import FrameStore, FrameStoreFull
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.save_util import load_from_pkl, save_to_pkl

CAMS = ("pixels/front", "pixels/wrist")
H = 6
OBS = spaces.Dict({CAMS[0]: spaces.Box(0, 255, (H, H, 3), np.uint8), CAMS[1]: spaces.Box(0, 255, (H, H, 3), np.uint8),
                   "state": spaces.Box(-1e6, 1e6, (3,), np.float32)})
ACT = spaces.Box(-1, 1, (2,), np.float32)


class Stream:
    """One actor's stream of episodes of ``length`` steps; every observation's pixels are random and kept by
    (actor, step-in-stream, which) so that a stored row can be checked against them. The state vector is
    (actor, step, episode)."""

    def __init__(self, actor: int, length: int, seed: int) -> None:
        self.actor, self.length, self.rng = actor, length, np.random.default_rng(seed)
        self.step, self.t, self.episode = 0, 0, 0
        self.current = self._frame()
        self.pixels: dict[tuple[int, str], dict[str, np.ndarray]] = {}  # (step, "obs"/"next") -> camera -> image

    def _frame(self) -> dict[str, np.ndarray]:
        return {c: self.rng.integers(0, 256, (H, H, 3), dtype=np.uint8) for c in CAMS}

    def batch(self, n: int) -> tuple:
        """The next ``n`` transitions as add_batch's arguments (positional, then keywords)."""
        obs, nxt, done, state = [], [], [], []
        first = self.step
        for _ in range(n):
            following = self._frame()
            self.pixels[(self.step, "obs")], self.pixels[(self.step, "next")] = self.current, following
            obs.append(self.current)
            nxt.append(following)
            state.append((self.actor, self.step, self.episode))
            self.t += 1
            done.append(self.t == self.length)
            self.step += 1
            if done[-1]:
                self.t, self.episode, self.current = 0, self.episode + 1, self._frame()
            else:
                self.current = following
        st = np.array(state, np.float32)
        o = {c: np.stack([f[c] for f in obs]) for c in CAMS} | {"state": st}
        x = {c: np.stack([f[c] for f in nxt]) for c in CAMS} | {"state": st + np.float32([0, 0.5, 0])}
        d = np.array(done)
        return ((o, x, np.zeros((n, 2), np.float32), st[:, 1].copy(), d, d.copy()),
                dict(intervened=np.zeros(n, np.uint8), clipped=np.zeros(n, np.uint8), actor=self.actor,
                     first_step=first))

    def feed(self, rb: FrameReplayBuffer, n: int) -> None:
        args, kwargs = self.batch(n)
        rb.add_batch(*args, **kwargs)


def _stored(rb: FrameReplayBuffer) -> np.ndarray:
    return np.arange(rb.buffer_size if rb.full else rb.pos)


def check_slots(rb: FrameReplayBuffer, streams: dict[int, Stream]) -> None:
    """Every stored slot's frames hold the pixels of its transition, are alive, and the store's counts are exactly
    the references the slots and pins hold."""
    slots = _stored(rb)
    for slot in slots:
        stream, step = streams[int(rb.provenance_actor[slot])], int(rb.provenance_step[slot])
        for which, ids in (("obs", rb.obs_frame), ("next", rb.next_frame)):
            assert rb.store.refs[ids[slot]] > 0
            for c in CAMS:
                np.testing.assert_array_equal(rb.store.frames[c][ids[slot]], stream.pixels[(step, which)][c])
    held = np.concatenate([rb.obs_frame[slots], rb.next_frame[slots], [p[0] for p in rb.pins.values()]])
    np.testing.assert_array_equal(rb.store.refs, np.bincount(held.astype(np.int64), minlength=rb.store.capacity))
    assert rb.store.live == len(np.unique(held))


def test_a_stream_of_three_episodes_stores_each_frame_once():
    rb = FrameReplayBuffer(100, OBS, ACT, device="cpu", min_episode_steps=5, max_streams=2)
    s = Stream(0, length=7, seed=1)
    for n in (3, 3, 3, 3, 3, 3, 3):  # batches cross the episodes' ends; 21 steps = 3 episodes
        s.feed(rb, n)
    assert rb.pos == 21 and rb.store.live == 21 + 3  # not 42: steps + episodes
    assert not rb.pins  # the last episode ended: nothing to continue
    same_episode = rb.dones[:20, 0] == 0
    np.testing.assert_array_equal(rb.obs_frame[1:21][same_episode], rb.next_frame[:20][same_episode])
    assert np.all(rb.obs_frame[1:21][~same_episode] != rb.next_frame[:20][~same_episode])
    check_slots(rb, {0: s})


def test_a_sample_carries_the_pixels_stored_for_its_rows():
    rb = FrameReplayBuffer(64, OBS, ACT, device="cpu", min_episode_steps=4, max_streams=2)
    streams = {0: Stream(0, 9, seed=2), 1: Stream(1, 5, seed=3)}
    for _ in range(8):
        for s in streams.values():
            s.feed(rb, 4)
    batch = rb.sample(128)
    assert batch.observations[CAMS[0]].dtype == torch.uint8 and batch.observations["state"].dtype == torch.float32
    assert list(batch.observations) == list(OBS.spaces)
    for row in range(128):
        actor, step, _ = batch.observations["state"][row].numpy().astype(int)
        for which, part in (("obs", batch.observations), ("next", batch.next_observations)):
            for c in CAMS:
                np.testing.assert_array_equal(part[c][row].numpy(), streams[actor].pixels[(step, which)][c])
        assert batch.next_observations["state"][row, 1].item() == step + 0.5
        assert batch.rewards[row, 0].item() == step


@pytest.mark.parametrize("sizes", [(7, 7), (13, 3)])  # equal rates; one actor sending ~4x as much (share eviction)
def test_overwritten_slots_free_their_frames(sizes):
    size = 50
    rb = FrameReplayBuffer(size, OBS, ACT, device="cpu", min_episode_steps=6, max_streams=2)
    streams = {0: Stream(0, 6, seed=4), 1: Stream(1, 11, seed=5)}
    added = 0
    while added < 10 * size:
        for s, n in zip(streams.values(), sizes):
            s.feed(rb, n)
            added += n
            slots = _stored(rb)
            starts = sum(int(np.count_nonzero(rb.provenance_step[slots][rb.provenance_actor[slots] == a] % s.length
                                              == 0)) for a, s in streams.items())
            assert len(slots) <= rb.store.live <= len(slots) + starts + 2 * 2  # the module docstring's bound
        check_slots(rb, streams)
    assert rb.full and rb.shares() == {"#0": 25, "#1": 25}
    assert rb.store.capacity == frame_capacity(size, 6, 2) == 50 + 9 + 4


def test_a_referenced_frame_is_never_freed():
    store = FrameStore({"a": (2, 2, 1)}, capacity=3)
    one = store.put({"a": np.full((2, 2, 1), 7, np.uint8)})
    store.incref(np.array([one, one]))  # three references
    store.decref(np.array([one, one]))
    assert store.live == 1 and store.refs[one] == 1
    two = store.put_many({"a": np.full((2, 2, 2, 1), 9, np.uint8)})
    assert one not in two and store.live == 3
    np.testing.assert_array_equal(store.get(np.array([one]))["a"][0], np.full((2, 2, 1), 7))
    with pytest.raises(FrameStoreFull, match="1 frames to store, 0 free of 3"):
        store.put({"a": np.zeros((2, 2, 1), np.uint8)})
    store.decref(np.array([one]))
    with pytest.raises(ValueError, match="more references"):
        store.decref(np.array([one]))
    with pytest.raises(ValueError, match="not alive"):
        store.incref(np.array([one]))
    assert store.put({"a": np.zeros((2, 2, 1), np.uint8)}) == one  # its id reused


def test_a_frame_lives_while_a_slot_references_it():
    rb = FrameReplayBuffer(4, OBS, ACT, device="cpu", min_episode_steps=100, max_streams=2)
    s0, s1 = Stream(0, 100, seed=6), Stream(1, 100, seed=7)
    s0.feed(rb, 2)
    s1.feed(rb, 2)  # full: two slots each
    shared = rb.pins[0][0]  # step 1's next observation = step 2's observation
    assert rb.store.refs[shared] == 2  # slot of step 1 and the pin
    s1.feed(rb, 2)  # actor 1 at its share evicts its own
    s0.feed(rb, 1)  # step 2 (row 0 continues: no new observation frame) evicts step 0
    assert rb.obs_frame[rb.provenance_step == 2][0] == shared and rb.store.refs[shared] == 2
    s0.feed(rb, 1)  # step 3 evicts step 1: the frame stays, step 2's observation
    assert rb.store.refs[shared] == 1
    check_slots(rb, {0: s0, 1: s1})
    live = rb.store.live
    s0.feed(rb, 1)  # step 4 evicts step 2: no slot references it any more, its id is free and reused at once
    assert rb.pins[0][0] == shared and rb.store.live == live == 6
    check_slots(rb, {0: s0, 1: s1})


def test_the_batch_form_and_a_continuation_that_does_not_fit():
    rb = FrameReplayBuffer(20, OBS, ACT, device="cpu", min_episode_steps=5, max_streams=2)
    s = Stream(0, 5, seed=8)
    (o, x, act, rew, done, timeout), kw = s.batch(7)
    frames, obs_frame, next_frame = pack_frames(o, x, done, list(CAMS), continues=False)
    assert len(frames[CAMS[0]]) == 7 + 2  # each row's next frame, and two episodes' first ones
    np.testing.assert_array_equal(obs_frame, [0, 1, 2, 3, 4, 6, 7])
    np.testing.assert_array_equal(next_frame, [1, 2, 3, 4, 5, 7, 8])
    rb.add_frames(frames, obs_frame, next_frame, o["state"], x["state"], act, rew, done, timeout, **kw)
    assert rb.pins[0][1] == 7
    (o, x, act, rew, done, timeout), kw = s.batch(2)
    frames, obs_frame, next_frame = pack_frames(o, x, done, list(CAMS), continues=True)
    assert obs_frame[0] == PREV and len(frames[CAMS[0]]) == 2  # the pinned frame is not sent again
    with pytest.raises(ValueError, match="holds no frame of that stream ending before step 8"):
        rb.add_frames(frames, obs_frame, next_frame, o["state"], x["state"], act, rew, done, timeout,
                      **(kw | {"first_step": 8}))
    rb.add_frames(frames, obs_frame, next_frame, o["state"], x["state"], act, rew, done, timeout, **kw)
    assert rb.store.live == 9 + 2
    check_slots(rb, {0: s})


def test_a_full_store_says_so():
    rb = FrameReplayBuffer(10, OBS, ACT, device="cpu", min_episode_steps=10, max_streams=1)  # 13 frames
    s = Stream(0, 1, seed=9)  # one-step episodes: 2 frames a transition, above the bound it was sized for
    with pytest.raises(FrameStoreFull, match="free of 13"):
        s.feed(rb, 10)


def test_a_pickled_or_copied_store_holds_its_live_frames_only():
    import pickle

    store = FrameStore({"a": (32, 32, 3), "b": (32, 32, 1)}, capacity=1000)
    rng = np.random.default_rng(0)
    frames = {"a": rng.integers(0, 256, (6, 32, 32, 3), np.uint8), "b": rng.integers(0, 256, (6, 32, 32, 1), np.uint8)}
    ids = store.put_many(frames)
    store.decref(ids[[1, 4]])  # two freed: four live
    blob = pickle.dumps(store)
    assert len(blob) < 10 * store.frame_bytes + 20_000 < store.nbytes // 50  # four frames, not a thousand
    for other in (pickle.loads(blob), store.copy()):
        assert other.live == 4 and np.array_equal(other.refs, store.refs) and other._top == store._top
        got = other.get(ids[[0, 2, 3, 5]])
        assert all(np.array_equal(got[k], frames[k][[0, 2, 3, 5]]) for k in frames)
        again = {k: v[:3] for k, v in frames.items()}
        assert np.array_equal(other.put_many(again), store.copy().put_many(again))  # the same ids reused
    twin = store.copy()
    twin.put_many({k: v[:1] for k, v in frames.items()})
    assert store.live == 4 and twin.live == 5  # independent


def test_save_load_and_the_checkpoint_copy():
    rb = FrameReplayBuffer(30, OBS, ACT, device="cpu", min_episode_steps=5, max_streams=2)
    streams = {0: Stream(0, 8, seed=10), 1: Stream(1, 6, seed=11)}
    for _ in range(6):
        for s in streams.values():
            s.feed(rb, 5)
    snapshot = copy_buffer(rb)
    assert snapshot.store is not rb.store and snapshot.pins == rb.pins
    with tempfile.TemporaryDirectory() as tmp:
        save_to_pkl(f"{tmp}/buffer.pkl", snapshot)
        for s in streams.values():  # the live buffer goes on meanwhile: the copy is not touched
            s.feed(rb, 5)
        back = load_from_pkl(f"{tmp}/buffer.pkl")
    assert isinstance(back, FrameReplayBuffer) and back.pins == snapshot.pins and back.pos == snapshot.pos
    for name in ("obs_frame", "next_frame", "provenance_step", "observations"):
        np.testing.assert_array_equal(getattr(back, name), getattr(snapshot, name))
    np.testing.assert_array_equal(back.store.refs, snapshot.store.refs)
    for c in CAMS:
        np.testing.assert_array_equal(back.store.frames[c], snapshot.store.frames[c])
    np.random.seed(0)
    a = snapshot.sample(32)
    np.random.seed(0)
    b = back.sample(32)
    for c in OBS.spaces:
        assert torch.equal(a.observations[c], b.observations[c])
        assert torch.equal(a.next_observations[c], b.next_observations[c])
    # the loaded buffer goes on with the streams' next batches (row 0 continues from the pins it kept)
    live = copy.copy(back)  # (an independent copy: ``back`` is compared below)
    replay = {a: Stream(a, s.length, seed=10 + a) for a, s in streams.items()}
    for _ in range(6):
        for s in replay.values():
            s.batch(5)  # the pixels and steps of the first six rounds, stored already
    before = live.store.live
    for s in replay.values():
        s.feed(live, 5)
    assert live.store.live - before <= 5 + 5 + 2  # one frame a step (and an episode's first): row 0 continued
    check_slots(live, replay)
    back.recount()
    np.testing.assert_array_equal(back.store.refs, snapshot.store.refs)


def test_sample_into_and_memory_optimisation_are_refused():
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        FrameReplayBuffer(10, OBS, ACT, device="cpu", optimize_memory_usage=True)
    with pytest.raises(ValueError, match="state vector"):
        FrameReplayBuffer(10, spaces.Dict({"cam": OBS[CAMS[0]]}), ACT, device="cpu")
    rb = FrameReplayBuffer(10, OBS, ACT, device="cpu")
    with pytest.raises(NotImplementedError):
        rb.sample_into(np.zeros((4, 10), np.float32))


def test_sb3_tqc_learns_from_it_and_saves_it(tmp_path):
    """sb3-contrib TQC builds the buffer (``replay_buffer_class``), stores through SB3's own ``add`` in ``learn``
    (episodes of 7 steps: frames once each), trains on its samples, and saves and loads it."""
    import gymnasium as gym
    from sb3_contrib import TQC

    side = 36  # (the smallest image SB3's NatureCNN takes)
    cam = spaces.Box(0, 255, (side, side, 3), np.uint8)
    obs_space = spaces.Dict({CAMS[0]: cam, CAMS[1]: cam, "state": spaces.Box(-1, 1, (3,), np.float32)})

    class Cameras(gym.Env):
        observation_space, action_space = obs_space, ACT

        def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
            super().reset(seed=seed)
            self.t = 0
            return self.observation_space.sample(), {}

        def step(self, act: Any) -> tuple[Any, float, bool, bool, dict]:
            self.t += 1
            return self.observation_space.sample(), float(act[0]), False, self.t == 7, {}

    model = TQC("MultiInputPolicy", Cameras(), buffer_size=100, learning_starts=10, batch_size=8, seed=0,
                replay_buffer_class=FrameReplayBuffer, replay_buffer_kwargs=dict(min_episode_steps=7, max_streams=1),
                policy_kwargs=dict(net_arch=[16, 16], n_critics=2, n_quantiles=5), device="cpu")
    model.set_logger(Logger(folder=None, output_formats=[]))  # (SB3's default leaves a directory in /tmp)
    before = [p.detach().clone() for p in model.critic.parameters()]
    model.learn(total_timesteps=28)
    rb = model.replay_buffer
    assert isinstance(rb, FrameReplayBuffer) and rb.pos == 28
    assert rb.store.live == 28 + 4  # 4 episodes of 7 steps: one frame a step and one an episode
    assert any(not torch.equal(a, b) for a, b in zip(before, model.critic.parameters()))
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert model.replay_buffer is not rb and model.replay_buffer.store.live == 32
    model.train(gradient_steps=1, batch_size=8)


def test_rlpd_sampling_draws_its_prior_half_with_the_right_pixels():
    rb = FrameReplayBuffer(64, OBS, ACT, device="cpu", min_episode_steps=4, max_streams=2, prior_fraction=0.5)
    streams = {0: Stream(0, 9, seed=12), 1: Stream(1, 5, seed=13)}
    for _ in range(4):
        for a, s in streams.items():
            args, kw = s.batch(4)
            rb.add_batch(*args, **(kw | {"intervened": np.full(4, a, np.uint8)}))  # actor 1: the prior data
    batch = rb.sample(64)
    actors = batch.observations["state"][:, 0].numpy().astype(int)
    assert np.all(actors[32:] == 1) and rb.sampled_prior == 32
    for row, (actor, step, _) in enumerate(batch.observations["state"].numpy().astype(int)):
        for c in CAMS:
            expected = streams[actor].pixels[(step, "next")][c]
            np.testing.assert_array_equal(batch.next_observations[c][row].numpy(), expected)


def test_the_benchmark_measures_both_buffers_and_writes_json(tmp_path, capsys):
    from khgrl.benchmarks.frame_replay import main

    out = tmp_path / "frame_replay.json"
    result = main(["--transitions", "200", "--side", "16", "--repeats", "2", "--out", str(out)])
    frame, sb3 = result["frame_replay"], result["sb3_dict"]
    assert frame["added"] >= 400 and frame["shares"] == {"#0": 100, "#1": 100}  # wrapped, shares evicted
    # 450 added: actor 0 holds steps 200-299 (one episode), actor 1 steps 50-149 (an episode starts at 100): each
    # slot's next frame, the two runs' first observations and actor 1's episode start (its pin is a slot's frame)
    assert frame["live_frames"] == 200 + 2 + 1
    assert frame["bytes_per_transition"] < 0.55 * sb3["bytes_per_transition"]
    assert frame["rss_bytes"] > 0 and sb3["rss_bytes"] > 0 and frame["sample_s"] > 0
    assert json.loads(out.read_text())["extrapolated"]["transitions"] == 100_000
    assert "extrapolated linearly from 200 to 100,000" in capsys.readouterr().out
