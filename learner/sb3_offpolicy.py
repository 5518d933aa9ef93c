"""The learner-algorithm interface (:mod:`khgrl.learner.algorithm`) for Stable-Baselines3's off-policy
algorithms: a subclass names the SB3 class, its policy class and its keyword arguments; everything else --
the :class:`~khgrl.learner.replay.StreamReplayBuffer`, a due iteration's ``train()``, weights for the actors,
checkpoint files, the snapshot and rollback of a training iteration that went non-finite -- is here once.

The model is ``ALGO(POLICY, SpacesEnv(task), **kwargs, replay_buffer_class=StreamReplayBuffer)`` (``POLICY``: the
subclass's :meth:`SB3OffPolicy.policy_class`, for TQC and SAC their ``"MlpPolicy"``). With ``[tqc] sampling
uniform`` the buffer draws the random numbers SB3's own does, so a seeded model is SB3's own; ``sampling rlpd``
passes ``replay_buffer_kwargs={"prior_fraction": 0.5}`` (RLPD's symmetric sampling,
:mod:`khgrl.learner.replay`). The actors get the policy's ``actor`` network (its ``state_dict``); an actor builds
the same policy class on the CPU and loads them into its ``actor``.

A camera task (a Dict observation space) gets DrQ's image policy and a
:class:`~khgrl.learner.frame_replay.FrameReplayBuffer` (:mod:`khgrl.learner.image_setup`).

One module of ~330 lines on purpose: the whole adapter between the learner-algorithm interface and SB3's off-policy
classes, used by every algorithm.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from khgrl.common.config.settings import TQCSettings
from khgrl.common.tasks.spaces import SpacesEnv
from khgrl.learner.algorithm import BUFFER_FILE, MODEL_FILE
from khgrl.learner.image_setup import buffer_frames, describe_space, image_policy, is_camera_space
from khgrl.learner.replay import StreamReplayBuffer, prior_fraction
from khgrl.learner.sb3_actor import SB3ActorPolicy, Untrained

__all__ = ["SB3OffPolicy", "SB3ActorPolicy", "Untrained", "LOSSES"]

LOSSES = ("train/critic_loss", "train/actor_loss", "train/ent_coef_loss")  # what SB3's SAC and TQC record


class SB3OffPolicy:
    """The learner-algorithm interface for an SB3 off-policy algorithm (subclasses: ``name``, :meth:`sb3_class`,
    :meth:`policy_class`, and :meth:`sb3_kwargs` where the run's settings map differently).

    :param model: the SB3 model, its replay buffer a :class:`StreamReplayBuffer`
    :param cuda_graph: train with each gradient step one CUDA graph (:mod:`khgrl.learner.cuda_graph`; the model on
        a CUDA device; not for a camera task, whose minibatches are not flat rows); False: SB3's own ``train()``
    :param compile_loss: without CUDA graphs, train with the step function and TQC's loss compiled
        (``--compile-loss``, opt-in: it rounds differently from SB3's ``train()``)
    """

    name: ClassVar[str] = ""

    def __init__(self, model: Any, cuda_graph: bool = False, compile_loss: bool = False) -> None:
        if not isinstance(model.replay_buffer, StreamReplayBuffer):
            raise TypeError(f"the learner's {self.name} model needs a StreamReplayBuffer")
        self.model = model
        self.gradient_steps = int(model.gradient_steps)
        self.batch_size = int(model.batch_size)
        self.graphed = None  # the CUDA-graph trainer (or, --compile-loss, its eager iteration), where one trains
        if (cuda_graph or compile_loss) and not is_camera_space(model.observation_space):  # (flat rows only)
            from khgrl.learner.cuda_graph import GraphedTrainer

            self.graphed = GraphedTrainer(model, graph=cuda_graph, compile_loss=compile_loss)

    @staticmethod
    def graphs_on(settings: TQCSettings, device: str) -> bool:
        """Whether the learner trains with CUDA graphs: ``cuda_graph`` set and the device a CUDA one.

        :param settings: the run's learner settings
        :param device: the torch device
        """
        return bool(getattr(settings, "cuda_graph", False)) and str(device).startswith("cuda")

    @staticmethod
    def compiled_on(settings: TQCSettings, device: str) -> bool:
        """Whether the learner trains with TQC's loss compiled: ``compile_loss`` set and the device the CPU.

        :param settings: the run's learner settings
        :param device: the torch device
        """
        return bool(getattr(settings, "compile_loss", False)) and str(device) == "cpu"

    # ------------------------------------------------------------------------------------ what a subclass says
    @classmethod
    def sb3_class(cls) -> type:
        """The SB3 algorithm class (imported when called)."""
        raise NotImplementedError

    @classmethod
    def policy_class(cls) -> type:
        """The SB3 policy class its ``"MlpPolicy"`` is (imported when called)."""
        raise NotImplementedError

    @classmethod
    def sb3_kwargs(cls, settings: TQCSettings, seed: int) -> dict[str, Any]:
        """Keyword arguments of the SB3 class (default: :meth:`TQCSettings.sb3_kwargs`, SB3's own names).

        :param settings: the run's learner settings
        :param seed: the model's seed
        """
        return settings.sb3_kwargs(seed)

    @classmethod
    def space_kwargs(cls, action_space: Any) -> dict[str, Any]:
        """Keyword arguments of the SB3 class that depend on the task's action space (default: none).

        :param action_space: the task's action space
        """
        return {}

    # ------------------------------------------------------------------------------------ building and loading
    @classmethod
    def build(cls, task: Any, settings: TQCSettings, seed: int, device: str) -> SB3OffPolicy:
        """A fresh model on the task's spaces (see :meth:`LearnerAlgorithm.build`); ``sampling rlpd``: its buffer
        samples RLPD's way (``replay_buffer_kwargs``, the module docstring)."""
        env = SpacesEnv(task)
        kwargs = {**cls.sb3_kwargs(settings, seed), **cls.space_kwargs(env.action_space), "device": device}
        fraction = prior_fraction(settings.sampling)
        if fraction > 0:  # (uniform: no buffer kwargs at all, the model SB3 builds without them)
            kwargs["replay_buffer_kwargs"] = {"prior_fraction": fraction}
        policy, extra = cls._policy(env.observation_space)
        buffer_class = StreamReplayBuffer
        if extra:  # a camera task (khgrl.learner.image_setup): DrQ's policy, each frame stored once
            from khgrl.learner.frame_replay import FrameReplayBuffer

            kwargs["policy_kwargs"] = {**kwargs.get("policy_kwargs", {}), **extra}
            buffer_class = FrameReplayBuffer
        model = cls.sb3_class()(policy, env, **kwargs, replay_buffer_class=buffer_class)
        return cls(model, cuda_graph=cls.graphs_on(settings, device), compile_loss=cls.compiled_on(settings, device))

    @classmethod
    def load(cls, directory: Path, task: Any, settings: TQCSettings, device: str, *,
             buffer: StreamReplayBuffer | None = None) -> SB3OffPolicy:
        """The model and replay buffer :meth:`save` wrote in ``directory`` (on ``device``, whatever it was saved
        from); with ``buffer``, the model alone (a model checkpoint) with that replay buffer. The buffer samples as
        the current ``settings.sampling`` says (its counters carry on)."""
        model = cls.sb3_class().load(Path(directory) / MODEL_FILE, env=SpacesEnv(task), device=device)
        if buffer is None:
            model.load_replay_buffer(Path(directory) / BUFFER_FILE)
        else:
            model.replay_buffer = buffer
        if not isinstance(model.replay_buffer, StreamReplayBuffer):
            raise ValueError(f"{directory}: the replay buffer is a {type(model.replay_buffer).__name__}, not a "
                             "StreamReplayBuffer")
        model.replay_buffer.prior_fraction = model.replay_buffer.check_fraction(prior_fraction(settings.sampling))
        return cls(model, cuda_graph=cls.graphs_on(settings, device), compile_loss=cls.compiled_on(settings, device))

    @classmethod
    def _policy(cls, observation_space: Any) -> tuple[type, dict[str, Any]]:
        """The policy class and the ``policy_kwargs`` beyond the run's for this observation space: the vector
        policy, or a camera task's DrQ image policy (:mod:`khgrl.learner.image_setup`)."""
        if not is_camera_space(observation_space):
            return cls.policy_class(), {}
        return image_policy(cls.name, observation_space)

    @classmethod
    def actor_policy(cls, observation_space: Any, action_space: Any, settings: TQCSettings) -> SB3ActorPolicy:
        """The policy class on the CPU with the run's network sizes (see :meth:`LearnerAlgorithm.actor_policy`)."""
        policy, extra = cls._policy(observation_space)
        return SB3ActorPolicy(policy(observation_space, action_space, lr_schedule=lambda _: settings.learning_rate,
                                     net_arch=list(settings.net_arch), optimizer_class=Untrained, **extra))

    @classmethod
    def checkpoint_policy(cls, model_file: Path, observation_space: Any, action_space: Any,
                          settings: TQCSettings) -> SB3ActorPolicy:
        """The whole policy (actor and critics) of a ``model.zip``, checked against these spaces and sizes."""
        from stable_baselines3.common.save_util import load_from_zip_file

        try:
            _, params, _ = load_from_zip_file(model_file, device="cpu", load_data=False)
        except Exception as exc:  # noqa: BLE001 - a damaged or foreign zip
            raise ValueError(f"cannot read the model ({type(exc).__name__}: {exc})") from None
        if not params or "policy" not in params:
            raise ValueError("no policy weights in it")
        wrapped = cls.actor_policy(observation_space, action_space, settings)
        state = params["policy"]
        want = {k: tuple(v.shape) for k, v in wrapped.policy.state_dict().items()}
        got = {k: tuple(v.shape) for k, v in state.items()}
        if want != got:
            bad = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
            raise ValueError(f"the policy does not fit this task's spaces (observation "
                             f"{describe_space(observation_space)}, action {action_space.shape[0]}) and net_arch "
                             f"{list(settings.net_arch)} of a "
                             f"{cls.name} policy: {bad[0]} is {got.get(bad[0])} in the checkpoint, "
                             f"{want.get(bad[0])} here")
        wrapped.policy.load_state_dict(state)
        wrapped.policy.set_training_mode(False)
        return wrapped

    # ------------------------------------------------------------------------------------ the learner's use
    @property
    def buffer(self) -> StreamReplayBuffer:
        """The model's replay buffer."""
        return self.model.replay_buffer

    @property
    def logger(self) -> Any:
        """SB3's logger of the model."""
        return self.model.logger

    def set_logger(self, folder: Path, formats: tuple[str, ...]) -> None:
        """SB3's logger writing ``formats`` to ``folder``."""
        from stable_baselines3.common.logger import configure

        self.model.set_logger(configure(str(folder), list(formats)))

    def store(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray, done: np.ndarray,
              timeout: np.ndarray, *, intervened: np.ndarray, clipped: np.ndarray, actor: int, first_step: int,
              frames: dict[str, np.ndarray] | None = None, obs_frame: np.ndarray | None = None,
              next_frame: np.ndarray | None = None) -> None:
        """One batch into the replay buffer (:meth:`StreamReplayBuffer.add_batch`, same arguments); a camera
        task's with its frames (``obs``/``next_obs`` its state vectors): :meth:`FrameReplayBuffer.add_frames`, row
        0's frame deduplicated against the stream's pin."""
        if frames is None:
            self.buffer.add_batch(obs, next_obs, action, reward, done, timeout, intervened=intervened,
                                  clipped=clipped, actor=actor, first_step=first_step)
            return
        self.buffer.add_frames(buffer_frames(self.buffer, frames), obs_frame, next_frame, obs, next_obs, action,
                               reward, done, timeout, intervened=intervened, clipped=clipped, actor=actor,
                               first_step=first_step, dedupe=True)

    def train(self, gradient_steps: int, *, timestep: int, sample_limit: int | None) -> None:
        """SB3's ``train(gradient_steps, batch_size)`` at environment step ``timestep``, sampling within
        ``sample_limit``."""
        for key in LOSSES:  # (the iteration records its own: :meth:`fault` reads them)
            self.model.logger.name_to_value.pop(key, None)
        self.model.num_timesteps = timestep
        self.buffer.sample_limit = sample_limit
        try:
            if self.graphed is not None:
                self.graphed.train(gradient_steps)
            else:
                self.model.train(gradient_steps=gradient_steps, batch_size=self.batch_size)
        finally:
            self.buffer.sample_limit = None

    def _optimizers(self) -> list[Any]:
        """The optimisers a training iteration steps: the actor's, the critics' and the entropy coefficient's."""
        from khgrl.learner.cuda_graph import optimizers

        return optimizers(self.model)

    def snapshot(self) -> dict[str, Any]:
        """The policy's ``state_dict`` (actor, critics, target critics), the optimisers' states, the entropy
        coefficient and SB3's update counter, copied (see :meth:`LearnerAlgorithm.snapshot`); with CUDA graphs,
        into preallocated device tensors once the optimisers have state (:meth:`GraphedTrainer.snapshot`)."""
        import copy

        if self.graphed is not None and (fast := self.graphed.snapshot()) is not None:
            return fast
        m = self.model
        ent = getattr(m, "log_ent_coef", None)
        return {"policy": {k: v.detach().clone() for k, v in m.policy.state_dict().items()},
                "optimizers": [copy.deepcopy(opt.state_dict()) for opt in self._optimizers()],
                "log_ent_coef": None if ent is None else ent.detach().clone(), "n_updates": m._n_updates}

    def restore(self, snapshot: dict[str, Any]) -> None:
        """Copy a :meth:`snapshot` back into the networks, optimisers and entropy coefficient (the tensors the
        optimisers hold stay the same objects).

        :param snapshot: what :meth:`snapshot` returned
        """
        import torch

        if snapshot.get("graphed"):
            self.graphed.restore(snapshot)
            return
        m = self.model
        m.policy.load_state_dict(snapshot["policy"])
        for opt, state in zip(self._optimizers(), snapshot["optimizers"]):
            opt.load_state_dict(state)
        if snapshot["log_ent_coef"] is not None:
            with torch.no_grad():
                m.log_ent_coef.copy_(snapshot["log_ent_coef"])
        m._n_updates = snapshot["n_updates"]
        if self.graphed is not None:  # (the optimisers hold new state tensors: the graphs are captured again)
            self.graphed.invalidate()

    def fault(self) -> str | None:
        """The first non-finite training loss of the last iteration, or parameter or buffer of the policy
        (actor, critics, target critics), or the entropy coefficient; None when all are finite."""
        import torch

        m = self.model
        logger = getattr(m, "_logger", None)  # (a model loaded from a checkpoint has none yet)
        values = logger.name_to_value if logger is not None else {}
        for key in LOSSES:
            if key in values and not np.isfinite(values[key]):
                return f"{key.rpartition('/')[2]} {values[key]}"
        if self.graphed is not None and self.graphed.finite:  # (checked on the device with the iteration's losses)
            return None
        tensors = [(k, v) for k, v in m.policy.state_dict().items() if v.is_floating_point()]
        ent = getattr(m, "log_ent_coef", None)
        if ent is not None:
            tensors.append(("log_ent_coef", ent))
        finite = torch.stack([torch.isfinite(t).all() for _, t in tensors])  # (one device sync, below)
        if bool(finite.all()):
            return None
        return f"parameter {tensors[int(torch.nonzero(~finite)[0, 0])][0]}"

    def policy_weights(self) -> dict[str, np.ndarray]:
        """The policy's ``actor`` network as CPU float32 arrays."""
        sd = self.model.policy.actor.state_dict()
        if self.graphed is None:
            return {k: v.detach().cpu().numpy().astype(np.float32, copy=True) for k, v in sd.items()}
        import torch  # (on a GPU: one copy to the host, not one per tensor)

        flat = torch.cat([v.detach().reshape(-1).float() for v in sd.values()]).cpu().numpy()
        out, at = {}, 0
        for k, v in sd.items():
            out[k] = flat[at:at + v.numel()].reshape(tuple(v.shape)).copy()
            at += v.numel()
        return out

    def save(self, directory: Path, *, buffer: bool | StreamReplayBuffer = True) -> list[Path]:
        """``model.zip`` (SB3's ``save``) and (``buffer``) ``replay_buffer.pkl`` (``save_replay_buffer``; a
        buffer given: that one, e.g. a copy taken while ingest was paused)."""
        from stable_baselines3.common.save_util import save_to_pkl

        directory = Path(directory)
        if self.graphed is not None:  # (the optimisers not capturable in the file, as SB3 writes them: loads anywhere)
            from khgrl.learner.cuda_graph import set_capturable

            set_capturable(self.model, False)
            try:
                self.model.save(directory / MODEL_FILE)
            finally:
                set_capturable(self.model, True)
        else:
            self.model.save(directory / MODEL_FILE)
        if buffer is False:
            return [directory / MODEL_FILE]
        save_to_pkl(directory / BUFFER_FILE, self.buffer if buffer is True else buffer)
        return [directory / MODEL_FILE, directory / BUFFER_FILE]
