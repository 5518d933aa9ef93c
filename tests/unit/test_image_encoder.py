"""The learner's image encoder (learner/image_encoder.py, image_policy.py, encoder_weights.py) on real SB3: a tiny
gymnasium env with two 32 x 32 x 3 cameras and a 4-d state drives sb3-contrib TQC, SB3's SAC and SAC-LN; DrQ's
sharing (one encoder, trained by the critic loss, the actor's features detached), the random shift, weights files
and a frozen trunk."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces
from khgrl.learner.encoder_weights import EncoderWeightsError, load_encoder_weights, read_weights
from khgrl.learner.image_encoder import ImageEncoder, RandomShift, conv_trunk
from khgrl.learner.image_policy import (
    DrQLayerNormSACPolicy,
    DrQSACPolicy,
    DrQTQCPolicy,
    image_policy_kwargs,
    sac_image_policy,
    sac_ln_image_policy,
    tqc_image_policy,
)
from sb3_contrib import TQC
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.logger import Logger

SIDE, EPISODE = 32, 20
HELPERS = [(TQC, tqc_image_policy, DrQTQCPolicy), (SAC, sac_image_policy, DrQSACPolicy),
           (SAC, sac_ln_image_policy, DrQLayerNormSACPolicy)]


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One torch thread here (the convolutions of tiny batches are slower on two threads of a busy machine)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


class TwoCameras(gym.Env):
    """Two random ``SIDE x SIDE x 3`` uint8 cameras and a 4-d state; reward ``-|a|^2``; episodes of ``EPISODE``
    steps. ``seen`` records each observation an action is taken on (what the replay buffer's ``observations``
    must hold, in order)."""

    observation_space = spaces.Dict({"front": spaces.Box(0, 255, (SIDE, SIDE, 3), np.uint8),
                                     "wrist": spaces.Box(0, 255, (SIDE, SIDE, 3), np.uint8),
                                     "state": spaces.Box(-1, 1, (4,), np.float32)})
    action_space = spaces.Box(-1, 1, (2,), np.float32)

    def __init__(self) -> None:
        self.seen: list[dict[str, np.ndarray]] = []
        self.t = 0

    def _obs(self) -> dict[str, np.ndarray]:
        rng = self.np_random
        return {"front": rng.integers(0, 256, (SIDE, SIDE, 3), dtype=np.uint8),
                "wrist": rng.integers(0, 256, (SIDE, SIDE, 3), dtype=np.uint8),
                "state": rng.uniform(-1, 1, 4).astype(np.float32)}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self.t = 0
        obs = self._obs()
        self.seen.append(obs)
        return obs, {}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        self.t += 1
        obs = self._obs()
        if self.t < EPISODE:
            self.seen.append(obs)
        return obs, float(-np.sum(np.square(action))), False, self.t >= EPISODE, {}


def _model(algo: type, helper, learning_starts: int = 100, **encoder):
    env = TwoCameras()
    policy, kwargs = helper(env.observation_space, features_dim=8, **encoder)
    model = algo(policy, env, policy_kwargs={**kwargs, "net_arch": [16, 16]}, learning_starts=learning_starts,
                 batch_size=8, buffer_size=400, train_freq=20, gradient_steps=2, seed=0)
    model.set_logger(Logger(folder=None, output_formats=[]))  # (SB3's default leaves a directory in /tmp)
    return model, env


def _encoder_state(encoder: ImageEncoder) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in encoder.state_dict().items()}


def _moved(before: dict[str, torch.Tensor], encoder: ImageEncoder, prefix: str) -> bool:
    after = encoder.state_dict()
    return all(not torch.equal(before[k], after[k]) for k in before if k.startswith(prefix) and "weight" in k)


def _fill(model) -> None:
    """Fill the buffer without training (the model's learning_starts is larger)."""
    model.learn(60)  # (3 rollouts of train_freq 20)
    assert model.replay_buffer.pos == 60


# ------------------------------------------------------------------------------------------ real SB3 learns with it
@pytest.mark.parametrize("algo,helper,policy_class", HELPERS, ids=["tqc", "sac", "sac_ln"])
def test_sb3_learns_a_few_hundred_steps_on_two_cameras_and_a_state(algo, helper, policy_class):
    model, env = _model(algo, helper)
    encoder = model.policy.actor.features_extractor
    before = _encoder_state(encoder)
    model.learn(300)
    assert type(model.policy) is policy_class and model.num_timesteps == 300
    assert model._n_updates == 20  # 10 trainings of 2 steps after step 100
    buffer = model.replay_buffer
    assert isinstance(buffer, DictReplayBuffer) and buffer.pos == 300
    for key in ("front", "wrist"):  # SB3 stored the cameras channel-first (its VecTransposeImage), uint8
        assert buffer.observations[key].dtype == np.uint8 and buffer.observations[key].shape == (400, 1, 3, SIDE, SIDE)
        stored = np.stack([o[key].transpose(2, 0, 1) for o in env.seen[:300]])
        np.testing.assert_array_equal(buffer.observations[key][:300, 0], stored)
    np.testing.assert_array_equal(buffer.observations["state"][:300, 0], np.stack([o["state"] for o in env.seen[:300]]))
    assert encoder is model.policy.critic.features_extractor  # one encoder object for actor and critics
    assert _moved(before, encoder, "trunks.") and _moved(before, encoder, "heads.")
    action, _ = model.predict(env.reset()[0], deterministic=True)  # an actor's channel-last observation
    assert action.shape == (2,) and np.all(np.abs(action) <= 1)


# ------------------------------------------------------------------------------------------ DrQ's gradient wiring
def _critic_loss(model, data) -> torch.Tensor:
    """The critic's loss on the buffer's actions (the target's value is irrelevant here: zeros)."""
    q = model.critic(data.observations, data.actions)
    return sum(x.square().mean() for x in (q if isinstance(q, tuple) else (q,)))


def _actor_loss(model, data) -> torch.Tensor:
    """SB3's actor loss: ``(alpha log pi - Q(s, pi(s))).mean()`` (TQC: Q the mean of the quantiles)."""
    actions_pi, log_prob = model.actor.action_log_prob(data.observations)
    q = model.critic(data.observations, actions_pi)
    if isinstance(q, torch.Tensor):  # TQC's quantiles
        q = q.mean(dim=2).mean(dim=1, keepdim=True)
    else:  # SAC's Q-values
        q = torch.cat(q, 1).min(1, keepdim=True)[0]
    return (0.1 * log_prob.reshape(-1, 1) - q).mean()


def _grads(module: torch.nn.Module) -> list[torch.Tensor | None]:
    return [p.grad for p in module.parameters()]


def _check_wiring(model) -> None:
    """The shared encoder is in the critic's optimiser only, and the actor loss's gradient does not reach it."""
    policy = model.policy
    encoder = policy.actor.features_extractor
    assert encoder is policy.critic.features_extractor and policy.critic_target.features_extractor is not encoder
    mine = {id(p) for p in encoder.parameters()}
    in_actor = {id(p) for g in policy.actor.optimizer.param_groups for p in g["params"]}
    in_critic = {id(p) for g in policy.critic.optimizer.param_groups for p in g["params"]}
    assert not mine & in_actor and mine <= in_critic
    assert {id(p) for p in policy.critic.parameters()} == in_critic
    policy.set_training_mode(True)
    data = model.replay_buffer.sample(8)
    policy.zero_grad(set_to_none=True)
    _actor_loss(model, data).backward()
    assert all(g is None for g in _grads(encoder))  # the actor loss alone does not reach the encoder ...
    assert all(g is not None for g in _grads(policy.actor.latent_pi))  # ... but does reach the actor
    policy.zero_grad(set_to_none=True)
    _critic_loss(model, data).backward()
    assert all(g is not None and g.abs().sum() > 0 for g in _grads(encoder))  # the critic loss reaches it
    assert all(g is None for g in _grads(policy.actor.latent_pi))


@pytest.mark.parametrize("algo,helper,policy_class", HELPERS, ids=["tqc", "sac", "sac_ln"])
def test_one_encoder_trained_by_the_critic_loss_only(algo, helper, policy_class, tmp_path):
    model, _ = _model(algo, helper, learning_starts=1000)
    _fill(model)
    _check_wiring(model)
    encoder, target = model.policy.actor.features_extractor, model.policy.critic_target.features_extractor
    before, target_before = _encoder_state(encoder), _encoder_state(target)
    model.train(gradient_steps=1, batch_size=8)
    assert _moved(before, encoder, "") and _moved(target_before, target, "")  # trained; the target Polyak-averaged
    assert target.training  # the target's encoder shifts the next observation too (DrQ)
    model.save(tmp_path / "model.zip")  # SB3's load builds the policy again: the same wiring
    again = algo.load(tmp_path / "model.zip", env=TwoCameras())
    again.replay_buffer = model.replay_buffer
    assert type(again.policy) is policy_class
    for key, value in model.policy.state_dict().items():
        assert torch.equal(value, again.policy.state_dict()[key])
    _check_wiring(again)


# ------------------------------------------------------------------------------------------ augmentation
def test_random_shift_is_a_per_sample_crop_in_training_and_the_identity_in_eval():
    images = torch.rand(6, 3, SIDE, SIDE)
    shift = RandomShift(pad=4, seed=1)
    out = shift(images)
    padded = torch.nn.functional.pad(images, (4, 4, 4, 4), mode="replicate")
    offsets = []
    for i in range(6):  # each sample is the padded image cropped at some offset in 0 .. 8
        found = [(dy, dx) for dy in range(9) for dx in range(9)
                 if torch.equal(out[i], padded[i, :, dy:dy + SIDE, dx:dx + SIDE])]
        assert found
        offsets.append(found[0])
    assert len(set(offsets)) > 1  # per sample, not one offset for the batch
    assert torch.equal(RandomShift(pad=4, seed=1)(images), out)  # seeded
    assert not torch.equal(RandomShift(pad=4, seed=2)(images), out)
    shift.eval()
    assert shift(images) is images


def test_the_encoder_shifts_in_train_mode_only():
    space = TwoCameras.observation_space
    one, two = ImageEncoder(space, 8, seed=1), ImageEncoder(space, 8, seed=2)
    two.load_state_dict(one.state_dict())
    plain = ImageEncoder(space, 8, augment=False)
    plain.load_state_dict(one.state_dict())
    obs = {k: torch.as_tensor(np.stack([s.sample() for _ in range(4)])).float() for k, s in space.spaces.items()}
    assert one.features_dim == 2 * 8 + 4
    with torch.no_grad():
        assert not torch.allclose(one(obs), two(obs))  # training mode: two seeds, two shifts
        assert torch.equal(plain(obs), plain(obs))
        one.eval(), two.eval()
        assert torch.equal(one(obs), two(obs)) and torch.equal(one(obs), plain(obs))  # eval: the identity
        assert torch.equal(one(obs)[:, -4:], obs["state"])  # the state after the cameras' features
        first = ImageEncoder(spaces.Dict({k: spaces.Box(0, 255, (3, SIDE, SIDE), np.uint8) if k != "state" else s
                                          for k, s in space.spaces.items()}), 8).eval()
        first.load_state_dict(one.state_dict())  # channel-first space, the same weights: the same features
        moved = {k: v.permute(0, 3, 1, 2) if v.ndim == 4 else v for k, v in obs.items()}
        assert torch.allclose(first(moved), one(obs))


def test_the_helpers_refuse_a_space_without_images():
    with pytest.raises(ValueError, match="Dict"):
        image_policy_kwargs(spaces.Box(-1, 1, (4,)))
    with pytest.raises(ValueError, match="no image"):
        tqc_image_policy(spaces.Dict({"state": spaces.Box(-1, 1, (4,))}))


# ------------------------------------------------------------------------------------------ weights files, frozen
def test_weights_file_round_trip_into_every_encoder_of_the_policy(tmp_path):
    source = conv_trunk(3)
    torch.save(source.state_dict(), tmp_path / "trunk.pt")  # one trunk: into every camera's
    model, _ = _model(TQC, tqc_image_policy)
    encoders = load_encoder_weights(model.policy, tmp_path / "trunk.pt")
    assert len(encoders) == 2 and model.policy.critic_target.features_extractor in encoders
    for encoder in encoders:
        for trunk in encoder.trunks.values():
            for key, value in source.state_dict().items():
                assert torch.equal(trunk.state_dict()[key], value)
    other = ImageEncoder(TwoCameras.observation_space, 8)  # per camera: each its own
    torch.save({f"{cam}.{k}": v for cam, t in other.trunks.items() for k, v in t.state_dict().items()},
               tmp_path / "cams.pt")
    load_encoder_weights(model.policy, tmp_path / "cams.pt")
    for cam in ("front", "wrist"):
        for key, value in other.trunks[cam].state_dict().items():
            assert torch.equal(model.policy.actor.features_extractor.trunks[cam].state_dict()[key], value)


def test_a_file_that_does_not_fit_is_refused_naming_the_key(tmp_path):
    encoder = ImageEncoder(TwoCameras.observation_space, 8)
    before = _encoder_state(encoder)
    state = conv_trunk(3).state_dict()
    state["2.weight"] = torch.zeros(32, 16, 3, 3)
    torch.save(state, tmp_path / "shape.pt")
    with pytest.raises(EncoderWeightsError, match=r"key 2\.weight has shape \(32, 16, 3, 3\) in the file, "
                                                  r"\(32, 32, 3, 3\)"):
        load_encoder_weights(encoder, tmp_path / "shape.pt")
    state = conv_trunk(3).state_dict()
    del state["6.bias"]
    state["8.weight"] = torch.zeros(1)
    torch.save(state, tmp_path / "keys.pt")
    with pytest.raises(EncoderWeightsError, match=r"missing keys 6\.bias; unexpected keys 8\.weight"):
        load_encoder_weights(encoder, tmp_path / "keys.pt")
    torch.save({"front." + k: v for k, v in conv_trunk(3).state_dict().items()}, tmp_path / "front.pt")
    with pytest.raises(EncoderWeightsError, match=r"missing keys wrist\.0\.bias"):
        load_encoder_weights(encoder, tmp_path / "front.pt")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(EncoderWeightsError, match="not a state_dict"):
        read_weights(tmp_path / "list.pt")
    torch.save({"trunk": RandomShift()}, tmp_path / "object.pt")  # a pickled object: weights_only refuses it
    with pytest.raises(EncoderWeightsError, match="cannot read"):
        read_weights(tmp_path / "object.pt")
    for key, value in encoder.state_dict().items():  # nothing was loaded
        assert torch.equal(value, before[key])


@pytest.mark.parametrize("built_frozen", [True, False], ids=["built-frozen", "frozen-on-load"])
def test_a_frozen_trunk_does_not_change_while_the_heads_train(built_frozen, tmp_path):
    torch.save(conv_trunk(3).state_dict(), tmp_path / "trunk.pt")
    model, _ = _model(TQC, tqc_image_policy, learning_starts=1000, frozen=built_frozen)
    _fill(model)
    encoder = model.policy.actor.features_extractor
    load_encoder_weights(model.policy, tmp_path / "trunk.pt", frozen=True)
    before = _encoder_state(encoder)
    model.train(gradient_steps=3, batch_size=8)
    assert all(not p.requires_grad for p in encoder.trunks.parameters())
    assert not any(m.training for m in encoder.trunks.modules()) and encoder.heads.training
    for key, value in encoder.state_dict().items():
        assert torch.equal(value, before[key]) == key.startswith("trunks."), key


def test_a_safetensors_file_needs_the_package(tmp_path):
    try:
        import safetensors  # noqa: F401
    except ImportError:
        (tmp_path / "trunk.safetensors").write_bytes(b"")
        with pytest.raises(EncoderWeightsError, match="needs the safetensors package"):
            read_weights(tmp_path / "trunk.safetensors")
    else:
        from safetensors.torch import save_file

        save_file(conv_trunk(3).state_dict(), str(tmp_path / "trunk.safetensors"))
        assert set(read_weights(tmp_path / "trunk.safetensors")) == set(conv_trunk(3).state_dict())


def test_an_actors_policy_on_the_tasks_channel_last_space_takes_the_learners_actor_weights():
    model, env = _model(TQC, tqc_image_policy, learning_starts=1000)  # the learner's: channel-first (SB3's transpose)
    policy, kwargs = tqc_image_policy(env.observation_space, features_dim=8)
    actor_side = policy(env.observation_space, env.action_space, lambda _: 1e-3, net_arch=[16, 16], **kwargs)
    actor_side.actor.load_state_dict(model.policy.actor.state_dict())
    actor_side.set_training_mode(False)
    obs = env.reset(seed=1)[0]
    model.policy.set_training_mode(False)
    np.testing.assert_allclose(actor_side.predict(obs, deterministic=True)[0],
                               model.predict(obs, deterministic=True)[0], rtol=1e-5, atol=1e-6)


def test_the_first_stride_keeps_the_trunk_output_about_drqs() -> None:
    """DrQ's 84 x 84 (and smaller) keep its stride 2; 128 x 128 gets 3: an output of 36 x 36 x 32, not 57 x 57 x 32."""
    from khgrl.learner.image_encoder import first_stride

    assert [first_stride(s, s) for s in (16, 84, 96, 128, 256)] == [2, 2, 2, 3, 6]
    out = {s: conv_trunk(3, first_stride(s, s))(torch.zeros(1, 3, s, s)).shape[1] for s in (84, 128)}
    assert out == {84: 32 * 35 * 35, 128: 32 * 36 * 36}
    space = spaces.Dict({"cam": spaces.Box(0, 255, (128, 128, 3), np.uint8), "state": spaces.Box(-1, 1, (4,))})
    assert ImageEncoder(space).heads["cam"][0].in_features == 32 * 36 * 36
