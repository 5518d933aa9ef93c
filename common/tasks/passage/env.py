"""The 2-D passage world as a Gymnasium environment (paper Section IV, Fig. 3; eqs. 7-11): the passage task
(:mod:`khgrl.common.tasks.passage.task`) behind the generic KGRL mapping (:class:`khgrl.common.tasks.kgrl_env.KGRLEnv`).

``gymnasium.make("khgrl/Passage-v0", scenario="high_cov" | "low_cov")`` after ``import khgrl.common.tasks.passage.env``.

One step at time index t (phase s = t / (T - 1), T = 400):

1. the exploration scale in force, L_t, is read from the scale model;
2. KGRL (no correction pending): the policy action a in [-1, 1]^2 is unscaled, xi = L_t (.) a, and the
   LC-NS-KMP gives the desired position P_t (eq. 5) inside the hard workspace constraints;
   KhGRL (a human correction P_h pending, :meth:`PassageEnv.set_correction`): P_h is projected onto the
   workspace box (counted), P_t = P_h, and the action the transition stores is
   a_h = clip(N_t^-1 (P_h - eta0_t) (/) L_t) (eq. 6; ``info["action"]``, ``info["intervened"]``);
3. the robot moves toward P_t at most ``speed`` per step and cannot cross a wall except through its gap;
4. reward r = r_a + r_o + r_p + r_T (eq. 7; eq. 11 without obstacle): r_a = -10 dp^T dp with
   dp = P_t - eta0_t the deviation the action causes (= N_t xi when no constraint is active), r_o = -10
   inside the obstacle, r_p = -10 while pressed against a wall, r_T = +200 on reaching the goal.

Episode end: success (terminated) at the goal; failure (terminated) when blocked for ``blocked_limit``
consecutive steps; truncation after T steps.

Observation (float32, 5): robot position (x, y), phase s, and the robot's offset from the KMP mean at
this phase (x - eta0_x(s), y - eta0_y(s)). The policy thus knows where it is, when it is, and how far it
already is from the demonstrated path.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields

import gymnasium as gym
import numpy as np
from khgrl.common.kmp.fit import KMPConfig
from khgrl.common.kmp.scale import ScaleModel
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.common.tasks.passage.scenarios import Scenario, get_scenario
from khgrl.common.tasks.passage.task import PassageRobot, make_task
from khgrl.common.tasks.world import TaskWorld, build_task_world

__all__ = ["PassageEnv", "PassageWorld", "ENV_ID", "build_world"]

ENV_ID = "khgrl/Passage-v0"


@dataclass(frozen=True)
class PassageWorld(TaskWorld):
    """The passage task's world, with its scenario (geometry) at hand."""

    scenario: Scenario | None = None


def _passage_world(scenario: str, task) -> PassageWorld:
    w = build_task_world(task)
    return PassageWorld(**{f.name: getattr(w, f.name) for f in fields(TaskWorld)}, scenario=get_scenario(scenario))


@functools.lru_cache(maxsize=8)
def _cached_world(scenario: str, demo_seed: int, config: KMPConfig) -> PassageWorld:
    return _passage_world(scenario, make_task(scenario, demo_seed=demo_seed, kmp_config=config))


def build_world(scenario: str = "high_cov", demos: np.ndarray | None = None, demo_seed: int = 0,
                config: KMPConfig = KMPConfig()) -> PassageWorld:
    """The scenario's world: its seeded demonstrations (or ``demos``) and the LC-NS-KMP fitted to them.
    Worlds from generated demonstrations are cached per process (fitting takes about a second)."""
    if demos is None:
        return _cached_world(scenario, demo_seed, config)
    from khgrl.common.tasks.demos import validate_demos

    demos = validate_demos(demos)
    if demos.shape[2] != 2:
        raise ValueError(f"the passage world is 2-D: demonstrations need O = 2, got {demos.shape}")
    return _passage_world(scenario, make_task(scenario, demos=demos, kmp_config=config))


class PassageEnv(KGRLEnv):
    """Point robot through two narrow passages (and around an obstacle in ``high_cov``), guided by KGRL.

    Args:
        scenario: "high_cov" (A) or "low_cov" (B).
        render_mode: None or "rgb_array" (the task's view, :class:`khgrl.common.tasks.render.TaskRenderer`).
        demos: optional (M, N, 2) demonstrations to use instead of the scenario's generated ones.
        demo_seed: seed of the generated demonstrations.
        kmp_config: GMM/GMR + LC-NS-KMP hyperparameters.
        scale_model: the exploration scale L (default: constant at the scenario's L0, i.e. KGRL).
        speed: robot speed limit per step (workspace units).
        blocked_limit: consecutive blocked steps that end the episode as a failure.
        start_noise: uniform noise on the start position (0: deterministic start).
    """

    def __init__(self, scenario: str = "high_cov", render_mode: str | None = None, *,
                 demos: np.ndarray | None = None, demo_seed: int = 0, kmp_config: KMPConfig = KMPConfig(),
                 scale_model: ScaleModel | None = None, speed: float = 0.01, blocked_limit: int = 20,
                 start_noise: float = 0.0) -> None:
        world = build_world(scenario, demos, demo_seed, kmp_config)
        inner = PassageRobot(world.scenario, speed, blocked_limit, start_noise)
        super().__init__(world=world, inner=inner, scale_model=scale_model, render_mode=render_mode)
        self.inner.reset()
        self._reset_state(self.inner.robot.copy(), self.inner.robot.copy())

    # the passage world's own names for the robot's state
    @property
    def scenario(self):
        return self.inner.scenario

    @property
    def robot(self) -> np.ndarray:
        return self.position

    @property
    def speed(self) -> float:
        return self.inner.speed

    @property
    def blocked_limit(self) -> int:
        return self.inner.blocked_limit

    @property
    def blocked_steps(self) -> int:
        return self.inner.blocked_steps

    @property
    def start_noise(self) -> float:
        return self.inner.start_noise


gym.register(id=ENV_ID, entry_point="khgrl.common.tasks.passage.env:PassageEnv", disable_env_checker=False)
