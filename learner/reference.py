"""Single-process reference run: sb3-contrib TQC on the passage world through SB3's own ``learn()`` loop.

This is what a user would run instead of the distributed system, and the baseline it must match in
sample efficiency: TQC with the paper's settings (Section IV: 2 x 256, lr 1e-3, tau 0.02, gamma 0.99,
train_freq 8, gradient_steps 8, automatic entropy coefficient); for KhGRL the scripted human corrects the
desired position in the given episodes and the replay buffer stores the human's action a_h in place of
the policy's (:class:`InterventionTQC`); in the low-covariance scenario the exploration scale L is refit
from each intervention.

It also measures what the single-process loop does to the environment's timing: the gap between
consecutive ``env.step`` calls, which includes the whole 8-gradient-step update every 8 steps.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from sb3_contrib import TQC
from stable_baselines3.common.callbacks import StopTrainingOnMaxEpisodes

from common.env import PassageEnv
from common.metrics import EpisodeAccumulator, EpisodeStats, write_episodes
from common.scale import ScaleModel
from human_bridge.scripted import PAPER_EPISODES, HumanCorrectionWrapper, ScriptedHuman, ScriptedHumanConfig

__all__ = ["ReferenceConfig", "InterventionTQC", "tqc_kwargs", "run_reference"]


def tqc_kwargs(seed: int) -> dict[str, Any]:
    """The paper's TQC settings (Section IV)."""
    return dict(
        learning_rate=1e-3,
        tau=0.02,
        gamma=0.99,
        train_freq=8,
        gradient_steps=8,
        ent_coef="auto",
        policy_kwargs=dict(net_arch=[256, 256]),
        learning_starts=100,
        batch_size=256,
        seed=seed,
        device="cpu",
        verbose=0,
    )


class InterventionTQC(TQC):
    """TQC that stores the human's action a_h (``info["action"]``) in place of the policy's for intervened steps."""

    n_intervened_stored = 0

    def _store_transition(self, replay_buffer, buffer_action, new_obs, reward, dones, infos):
        buffer_action = np.array(buffer_action, copy=True)
        for i, info in enumerate(infos):
            if info.get("intervened"):
                buffer_action[i] = info["action"]
                self.n_intervened_stored += 1
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)


@dataclass(frozen=True)
class ReferenceConfig:
    scenario: str = "high_cov"
    method: str = "khgrl"  # "khgrl" (scripted human) or "kgrl" (no human)
    episodes: int = 60
    seed: int = 0
    human_episodes: tuple[int, ...] = PAPER_EPISODES
    human_noise: float = 0.0

    def __post_init__(self) -> None:
        if self.method not in ("kgrl", "khgrl"):
            raise ValueError(f"method must be 'kgrl' or 'khgrl', got {self.method!r}")
        if self.episodes < 1:
            raise ValueError("episodes must be >= 1")


class _StatsWrapper(gym.Wrapper):
    """Collects EpisodeStats and the wall-clock gap between consecutive steps (environment stalls)."""

    def __init__(self, env: gym.Env, on_episode) -> None:
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


def build_env(config: ReferenceConfig):
    """The passage world with, for KhGRL, the scripted human applying corrections before each step."""
    base = PassageEnv(config.scenario)
    sc = base.scenario
    base.mapping.scale_model = ScaleModel(sc.default_scale, dim=2)
    base.mapping.refresh_scale()
    env: gym.Env = base
    if config.method == "khgrl":
        human = ScriptedHuman(sc, ScriptedHumanConfig(episodes=config.human_episodes, noise=config.human_noise, seed=config.seed))

        def on_release(segment):
            if sc.learn_scale:
                base.mapping.update_scale(np.array([d["xi_h"] for d in segment]), np.array([d["phase"] for d in segment]))

        env = HumanCorrectionWrapper(env, human, on_release=on_release)
    return base, env


def run_reference(config: ReferenceConfig, run_dir: str | Path, progress: bool = True) -> list[EpisodeStats]:
    """Train TQC for ``config.episodes`` episodes; write config, per-episode metrics and timing to run_dir."""
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
    model = InterventionTQC("MlpPolicy", env, **tqc_kwargs(config.seed))
    t0 = time.perf_counter()
    model.learn(
        total_timesteps=config.episodes * base.horizon,
        callback=StopTrainingOnMaxEpisodes(max_episodes=config.episodes, verbose=0),
    )
    wall = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    gaps = np.asarray(env.gaps)
    summary = {
        "wall_time_s": wall,
        "env_steps": int(model.num_timesteps),
        "gradient_steps": int(model._n_updates),
        "intervened_transitions_stored": int(model.n_intervened_stored),
        "step_gap_ms": {
            "p50": float(np.percentile(gaps, 50) * 1e3) if gaps.size else None,
            "p99": float(np.percentile(gaps, 99) * 1e3) if gaps.size else None,
            "max": float(gaps.max() * 1e3) if gaps.size else None,
        },
        "successes": int(sum(e.success for e in episodes)),
        "first_success": next((e.episode for e in episodes if e.success), None),
        "final_scale_table_max": None if base.mapping.scale_table is None else base.mapping.scale_table.max(axis=0).tolist(),
    }
    write_episodes(run_dir, episodes, {"reference": asdict(config), "tqc": {k: str(v) for k, v in tqc_kwargs(config.seed).items()}})
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if base.mapping.scale_table is not None:
        np.save(run_dir / "scale_table.npy", base.mapping.scale_table)
    return episodes
