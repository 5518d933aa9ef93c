"""The scripted human's decision: a reproducible stand-in for a person who drags the robot's desired position
(:class:`ScriptedHuman`), and its single-process use (:class:`HumanCorrectionWrapper`). Shared by the human client
``khgrl human scripted`` (:mod:`khgrl.human_bridge.scripted`, which publishes it as correction messages) and the
single-process reference (:mod:`khgrl.learner.baseline`).

In the given episodes it asks the task's ``scripted_human`` (:class:`khgrl.common.tasks.api.Task`) for P_h at each
step's KMP mean; optional seeded noise imitates an unsteady hand; None releases. The passage world's
(:class:`khgrl.common.tasks.passage.task.PassageGuide`) knows a safe path through the gaps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import gymnasium as gym
import numpy as np
from khgrl.common.config.settings import PAPER_EPISODES
from khgrl.common.tasks.api import call_scripted_human, scripted_human_inputs

__all__ = ["ScriptedHuman", "ScriptedHumanConfig", "HumanCorrectionWrapper", "WholeEpisode"]


@dataclass(frozen=True)
class ScriptedHumanConfig:
    episodes: tuple[int, ...] = PAPER_EPISODES  # 1-based episode numbers in which the human helps
    window: tuple[float, float] | None = None  # passage world: x-range where it helps (default: the scenario's)
    noise: float = 0.0  # std of Gaussian noise on P_h (workspace units)
    seed: int = 0
    finish: bool = False  # once it takes over in an episode, it holds every remaining step (--takeover finish)


class ScriptedHuman:
    """Decides P_h (or None) from what a person watching the screen sees: episode, step, robot and KMP mean.

    :param guide: the task's ``scripted_human`` (``mean`` -> P_h or None, and optionally ``step``, ``phase``,
        ``position``, ``obs``), or a passage scenario (its name).
    :param config: episodes, noise and seed (``window``: the passage world's only).
    """

    def __init__(self, guide: Callable[[np.ndarray], np.ndarray | None] | Any,
                 config: ScriptedHumanConfig = ScriptedHumanConfig()) -> None:
        if not callable(guide):  # a passage scenario or its name: the passage world's guide
            from khgrl.common.tasks.passage.scenarios import get_scenario
            from khgrl.common.tasks.passage.task import PassageGuide

            guide = PassageGuide(get_scenario(guide) if isinstance(guide, str) else guide, config.window)
        self.guide = guide
        self.inputs = scripted_human_inputs(guide)  # what it asks for besides the mean (from its signature, once)
        self.config = config
        self._rng = np.random.default_rng(config.seed)
        self._taken: set[int] = set()  # (finish) the episodes it has taken over in

    def path_y(self, x: float) -> float:
        """The passage world's safe path at workspace x."""
        return self.guide.path_y(x)

    def active_in(self, episode: int) -> bool:
        return episode in self.config.episodes

    def correction(self, episode: int, mean: np.ndarray, *, step: int = 0, phase: float | None = None,
                   position: np.ndarray | None = None, obs: np.ndarray | None = None) -> np.ndarray | None:
        """P_h for this step, or None.

        :param episode: the episode (1-based).
        :param mean: the KMP mean eta0_t at the step (the red line).
        :param step: the step t the correction is for.
        :param phase: its phase s_t.
        :param position: where the robot is before the step (None: at the mean).
        :param obs: the environment's latest observation (None: none yet).

        With ``finish`` (HIL-SERL's human, ``--takeover finish``): from the guide's first P_h in an episode on,
        every later step of that episode is held -- the guide's P_h where it helps, the step's KMP mean elsewhere.
        """
        if not self.active_in(episode):
            return None
        mean = np.asarray(mean, dtype=np.float64)
        position = mean.copy() if position is None else np.asarray(position, dtype=np.float64)
        p_h = call_scripted_human(self.guide, mean, step=int(step), phase=phase, position=position, obs=obs,
                                  names=self.inputs)
        if self.config.finish and p_h is not None:
            self._taken.add(episode)
        elif self.config.finish and episode in self._taken:
            p_h = mean  # (finishing what it took over: the demonstrated path to the task's end)
        if p_h is None:
            return None
        p_h = np.asarray(p_h, dtype=np.float64).reshape(-1)
        if p_h.shape != np.shape(mean) or not np.all(np.isfinite(p_h)):
            raise ValueError(f"the task's scripted human gave {p_h}, expected {np.size(mean)} finite values")
        if self.config.noise > 0:
            p_h = p_h + self._rng.normal(0.0, self.config.noise, size=p_h.size)
        return p_h


class WholeEpisode:
    """A scripted human that holds every step of its episodes (``--takeover episode`` under ``--method hil-serl``):
    the task's guide's P_h where the guide helps, the KMP mean of the step -- the demonstrated path -- everywhere
    else. Under HIL-SERL's takeover that makes each of its episodes a demonstration driven end to end by the human.

    :param guide: the task's scripted human (or its ``takeover``)
    """

    def __init__(self, guide: Callable[..., np.ndarray | None]) -> None:
        self.guide = guide
        self.names = scripted_human_inputs(guide)

    def __call__(self, mean: np.ndarray, **inputs: Any) -> np.ndarray:
        p_h = call_scripted_human(self.guide, mean, names=self.names, **inputs)
        return np.array(mean, dtype=np.float64) if p_h is None else p_h


class HumanCorrectionWrapper(gym.Wrapper):
    """Single-process use: asks a human (scripted) for P_h before every step and applies it to the env.

    Counts episodes from 1 (the paper's numbering). ``on_release`` is called with the intervention's
    steps when a correction stream ends, e.g. to refit the exploration scale.
    """

    def __init__(self, env: gym.Env, human: ScriptedHuman, on_release=None) -> None:
        super().__init__(env)
        self.human = human
        self.episode = 0
        self.on_release = on_release
        self._segment: list[dict] = []

    def reset(self, **kwargs):
        self._flush()
        self.episode += 1
        return self.env.reset(**kwargs)

    def step(self, action):
        base = self.env.unwrapped
        t = min(base.t, base.horizon - 1)
        p_h = self.human.correction(self.episode, base.mapping.mean(t), step=t, phase=float(base.mapping.phases[t]),
                                    position=base.position, obs=getattr(base, "_inner_obs", None))
        base.set_correction(p_h)
        obs, reward, terminated, truncated, info = self.env.step(action)
        if info.get("intervened"):
            self._segment.append({"xi_h": info["xi_h"], "phase": info["phase"], "position": info["desired"]})
        elif self._segment:
            self._flush()
        if terminated or truncated:
            base.set_correction(None)
            self._flush()
        return obs, reward, terminated, truncated, info

    def _flush(self) -> None:
        if self._segment and self.on_release is not None:
            self.on_release(self._segment)
        self._segment = []
