"""Single-process baseline: sb3-contrib TQC on the passage world through SB3's own ``learn()`` loop.

This is what a user would run instead of the distributed system (``khgrl reference``), and the baseline it
must match in sample efficiency: TQC with the run's settings (:class:`khgrl.common.config.settings.TQCSettings`, the one
source the learner uses too: the paper's 2 x 256, lr 1e-3, tau 0.02, gamma 0.99, train_freq 8,
gradient_steps 8, automatic entropy coefficient); for KhGRL the scripted human
(:mod:`khgrl.common.tasks.scripted_human`) corrects the desired position in the given episodes and the replay
buffer stores the human's action a_h in place of the policy's (:class:`InterventionTQC`); in the low-covariance
scenario the exploration scale L is refit from each intervention.

It also measures what the single-process loop does to the environment's timing: the gap between
consecutive ``env.step`` calls, which includes the whole training iteration every ``train_freq`` steps.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch
from khgrl.common.config.settings import REFERENCE_METHODS, RunConfig, TQCSettings
from khgrl.common.kmp.scale import ScaleModel
from khgrl.common.metrics import EpisodeAccumulator, EpisodeStats, write_episodes
from khgrl.common.tasks.passage.env import PassageEnv
from khgrl.common.tasks.scripted_human import HumanCorrectionWrapper, ScriptedHuman, ScriptedHumanConfig
from sb3_contrib import TQC
from stable_baselines3.common.callbacks import StopTrainingOnMaxEpisodes
from stable_baselines3.common.logger import configure

__all__ = ["ReferenceConfig", "InterventionTQC", "build_env", "run_reference"]


class InterventionTQC(TQC):
    """TQC that stores the human's action a_h (``info["action"]``) in place of the policy's for intervened
    steps, and counts its gradient steps."""

    n_intervened_stored = 0
    gradient_steps_done = 0

    def _store_transition(self, replay_buffer, buffer_action, new_obs, reward, dones, infos):
        # SB3 has no public hook between the environment step and the replay buffer: this override is it
        buffer_action = np.array(buffer_action, copy=True)
        for i, info in enumerate(infos):
            if info.get("intervened"):
                buffer_action[i] = info["action"]
                self.n_intervened_stored += 1
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """TQC's training iteration, counted.

        :param gradient_steps: gradient steps of this iteration
        :param batch_size: minibatch size
        """
        super().train(gradient_steps, batch_size)
        self.gradient_steps_done += gradient_steps


_RUN = RunConfig()  # the one source of the defaults


@dataclass(frozen=True)
class ReferenceConfig:
    """One single-process run: the settings of a :class:`~khgrl.common.config.settings.RunConfig` it uses (and
    its defaults)."""

    scenario: str = _RUN.scenario
    method: str = _RUN.method  # "khgrl" (scripted human) or "kgrl" (no human)
    episodes: int = _RUN.episodes
    seed: int = _RUN.seed
    human_episodes: tuple[int, ...] = _RUN.human_episodes
    human_noise: float = _RUN.human_noise
    tqc: TQCSettings = field(default_factory=TQCSettings)

    @classmethod
    def from_run(cls, cfg: RunConfig) -> "ReferenceConfig":
        """The reference run of a run configuration (``khgrl reference``'s flags are RunConfig's)."""
        return cls(**{f: getattr(cfg, f) for f in ("scenario", "method", "episodes", "seed", "human_episodes",
                                                      "human_noise", "tqc")})

    def __post_init__(self) -> None:
        if self.method not in REFERENCE_METHODS:
            raise ValueError(f"the single-process reference runs {', '.join(REFERENCE_METHODS)}, not {self.method!r} "
                             "(run it through khgrl up)")
        if self.episodes < 1:
            raise ValueError("episodes must be >= 1")
        self.tqc.validate()


class _StatsWrapper(gym.Wrapper):
    """Collects EpisodeStats and the wall-clock gap between consecutive steps (environment stalls)."""

    def __init__(self, env: gym.Env, on_episode: Callable[[EpisodeStats], None]) -> None:
        super().__init__(env)
        self.acc = EpisodeAccumulator()
        self.on_episode = on_episode
        self.gaps: list[float] = []
        self._last_return: float | None = None
        self._t_episode = 0.0

    def reset(self, **kwargs):
        self.acc.start()
        self._t_episode = time.perf_counter()
        self._last_return = None
        return self.env.reset(**kwargs)

    def step(self, action):
        now = time.perf_counter()
        if self._last_return is not None:
            self.gaps.append(now - self._last_return)
        out = self.env.step(action)
        obs, reward, terminated, truncated, info = out
        self.acc.add(reward, info)
        if terminated or truncated:
            self.on_episode(self.acc.finish(time.perf_counter() - self._t_episode))
        self._last_return = time.perf_counter()
        return out


def build_env(config: ReferenceConfig) -> tuple[PassageEnv, gym.Env]:
    """The passage world with, for KhGRL, the scripted human applying corrections before each step.

    :param config: the run
    """
    base = PassageEnv(config.scenario)
    sc = base.scenario
    base.mapping.scale_model = ScaleModel(sc.default_scale, dim=2)
    base.mapping.refresh_scale()
    env: gym.Env = base
    if config.method == "khgrl":
        human = ScriptedHuman(sc, ScriptedHumanConfig(episodes=config.human_episodes, noise=config.human_noise,
                                                      seed=config.seed))

        def on_release(segment):
            if sc.learn_scale:
                base.mapping.update_scale(np.array([d["xi_h"] for d in segment]),
                                          np.array([d["phase"] for d in segment]))

        env = HumanCorrectionWrapper(env, human, on_release=on_release)
    return base, env


def _summary(model: InterventionTQC, wall: float, gaps: np.ndarray, episodes: list[EpisodeStats],
             base: PassageEnv) -> dict[str, Any]:
    def pct(q: float) -> float | None:
        return float(np.percentile(gaps, q) * 1e3) if gaps.size else None

    table = base.mapping.scale_table
    return {
        "wall_time_s": wall,
        "env_steps": int(model.num_timesteps),
        "gradient_steps": int(model.gradient_steps_done),
        "intervened_transitions_stored": int(model.n_intervened_stored),
        "step_gap_ms": {"p50": pct(50), "p99": pct(99), "max": float(gaps.max() * 1e3) if gaps.size else None},
        "successes": int(sum(e.success for e in episodes)),
        "first_success": next((e.episode for e in episodes if e.success), None),
        "final_scale_table_max": None if table is None else table.max(axis=0).tolist(),
    }


def run_reference(config: ReferenceConfig, run_dir: str | Path, progress: bool = True) -> list[EpisodeStats]:
    """Train TQC for ``config.episodes`` episodes; write config, per-episode metrics and timing to run_dir.

    :param config: the run
    :param run_dir: where config.json, episodes.csv/json, summary.json (and scale_table.npy) go, and SB3's log
        (sb3/progress.csv)
    :param progress: show a progress bar
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    episodes: list[EpisodeStats] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.episodes, desc=f"{config.scenario}/{config.method}/seed{config.seed}", unit="ep")

    def on_episode(st: EpisodeStats) -> None:
        episodes.append(st)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(ret=f"{st.ret:.0f}", ok=int(st.success), iv=st.intervention_steps)

    base, env = build_env(config)
    env = _StatsWrapper(env, on_episode)
    kwargs = config.tqc.sb3_kwargs(config.seed)
    model = InterventionTQC("MlpPolicy", env, **kwargs)
    model.set_logger(configure(str(run_dir / "sb3"), ["csv"]))  # (SB3's default makes a directory in /tmp)
    t0 = time.perf_counter()
    model.learn(total_timesteps=config.episodes * base.horizon,
                callback=StopTrainingOnMaxEpisodes(max_episodes=config.episodes, verbose=0))
    wall = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    summary = _summary(model, wall, np.asarray(env.gaps), episodes, base)
    write_episodes(run_dir, episodes, {"reference": asdict(config), "tqc": {k: str(v) for k, v in kwargs.items()}})
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if base.mapping.scale_table is not None:
        np.save(run_dir / "scale_table.npy", base.mapping.scale_table)
    return episodes
