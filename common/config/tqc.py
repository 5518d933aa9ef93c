"""The learner's settings, :class:`TQCSettings` (the paper's TQC settings, Section IV; the learner's whatever its
algorithm): the fields and their flags (:mod:`khgrl.common.config.settings` builds the flags and files of all)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from khgrl.common.config.fields import _LA, _LAR, _LR, _opt

__all__ = ["TQCSettings", "SAMPLINGS", "DEVICES"]

SAMPLINGS = ("uniform", "rlpd")
DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class TQCSettings:
    """sb3-contrib TQC as in the paper (Section IV): 2 x 256, lr 1e-3, tau 0.02, gamma 0.99, train_freq 8,
    gradient_steps 8, automatic entropy coefficient."""

    learning_rate: float = _opt(1e-3, "TQC learning rate", roles=_LR)
    tau: float = _opt(0.02, "soft target update rate", roles=_LR)
    gamma: float = _opt(0.99, "discount factor", roles=_LR)
    train_freq: int = _opt(8, "transitions per training iteration", roles=_LAR)
    gradient_steps: int = _opt(8, "gradient steps per training iteration", roles=_LR)
    ent_coef: str = _opt("auto", "entropy coefficient ('auto': learned)", roles=_LR)
    net_arch: tuple[int, ...] = _opt((256, 256), "hidden layer sizes of actor and critics", roles=_LAR)
    learning_starts: int = _opt(100, "uniform random actions (and no training) for the first N transitions",
                                roles=_LAR)
    batch_size: int = _opt(256, "minibatch size of a gradient step", roles=_LR)
    buffer_size: int = _opt(200_000, "replay buffer capacity (transitions)", roles=_LR)
    sampling: str = _opt("uniform", "how a minibatch is drawn: uniform (SB3's, the paper's) or rlpd (RLPD's symmetric "
                                    "sampling: half of each batch from the prior data -- demonstrations replayed as "
                                    "transitions and the human's interventions -- half from all data)", SAMPLINGS,
                         roles=_LA)
    cta_ratio: int = _opt(1, "--algo sac_cta: critic updates per actor update in each gradient step (HIL-SERL's "
                             "cta_ratio: 2; 1: SAC's one each)", roles=_LR)
    backup_entropy: bool = _opt(True, "--algo sac_cta: the entropy term in the critics' target (SAC's; HIL-SERL: "
                                      "--no-backup-entropy)", roles=_LR)
    device: str = _opt("auto", "where the learner trains: auto (cuda if torch sees a GPU, else cpu), cpu or cuda; "
                               "weights always go to actors as CPU float32 arrays", DEVICES, roles=_LR)
    cuda_graph: bool = _opt(True, "on a CUDA device, each gradient step is one CUDA graph replayed (the library's "
                                  "step, captured; --no-cuda-graph: SB3's own train()); no effect on the CPU",
                            roles=_LR)
    compile_loss: bool = _opt(False, "on the CPU, TQC's quantile Huber loss compiled by torch.compile (a C++ "
                                     "compiler needed; about a minute at the first step; faster steps that round "
                                     "differently from SB3's train(), so seeded runs differ: opt-in)", roles=_LR)

    def sb3_kwargs(self, seed: int) -> dict[str, Any]:
        """Keyword arguments of ``sb3_contrib.TQC("MlpPolicy", env, **kwargs)``."""
        return dict(learning_rate=self.learning_rate, tau=self.tau, gamma=self.gamma, train_freq=self.train_freq,
                    gradient_steps=self.gradient_steps, ent_coef=self.ent_coef,
                    policy_kwargs=dict(net_arch=list(self.net_arch)), learning_starts=self.learning_starts,
                    batch_size=self.batch_size, buffer_size=self.buffer_size, seed=seed, device=self.device,
                    verbose=0)

    def validate(self) -> None:
        for name in ("train_freq", "gradient_steps", "batch_size", "buffer_size", "cta_ratio"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.learning_starts < 0 or not self.net_arch or min(self.net_arch) < 1:
            raise ValueError("learning_starts must be >= 0 and net_arch a list of positive sizes")
