"""The 2-D passage world as a Gymnasium environment (paper Section IV, Fig. 3; eqs. 7-11).

``gymnasium.make("khgrl/Passage-v0", scenario="high_cov" | "low_cov")`` after ``import common.env``.

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
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from common.kgrl import KGRLMapping
from common.kmp import LCNSKMP
from common.model import KMPConfig, box_constraints, fit_model
from common.scale import ScaleModel
from common.scenarios import Scenario, get_scenario, make_demos
from common.spaces import action_space, observation_space

__all__ = ["PassageEnv", "PassageWorld", "ENV_ID", "build_world"]

ENV_ID = "khgrl/Passage-v0"

R_ACTION = 10.0
R_OBSTACLE = -10.0
R_PASSAGE = -10.0
R_GOAL = 200.0


@dataclass(frozen=True)
class PassageWorld:
    """Everything an episode needs that does not change during a run: geometry, demos and the KMP."""

    scenario: Scenario
    demos: np.ndarray
    model: LCNSKMP
    config: KMPConfig


@functools.lru_cache(maxsize=8)
def _cached_world(scenario: str, demo_seed: int, config: KMPConfig) -> PassageWorld:
    sc = get_scenario(scenario)
    demos = make_demos(sc, seed=demo_seed)
    return _world_from(sc, demos, config)


def _world_from(sc: Scenario, demos: np.ndarray, config: KMPConfig) -> PassageWorld:
    m = sc.workspace_margin
    model, _ = fit_model(demos, config, box_constraints([m, m], [1 - m, 1 - m]))
    return PassageWorld(scenario=sc, demos=demos, model=model, config=config)


def build_world(
    scenario: str = "high_cov", demos: np.ndarray | None = None, demo_seed: int = 0, config: KMPConfig = KMPConfig()
) -> PassageWorld:
    """The scenario's world: its seeded demonstrations (or ``demos``) and the LC-NS-KMP fitted to them.
    Worlds from generated demonstrations are cached per process (fitting takes about a second)."""
    if demos is None:
        return _cached_world(scenario, demo_seed, config)
    from common.demos import validate_demos

    demos = validate_demos(demos)
    if demos.shape[2] != 2:
        raise ValueError(f"the passage world is 2-D: demonstrations need O = 2, got {demos.shape}")
    return _world_from(get_scenario(scenario), demos, config)


def _segment_blocked(p: np.ndarray, q: np.ndarray, walls) -> tuple[np.ndarray, bool]:
    """Move p -> q unless a wall is in the way: then stop just short of it (blocked).

    A wall is the line x = wall.x minus its open gap. The robot may stand on the line only inside the gap
    (it passed through it); from there, moving along the line is clamped to the gap, and leaving the line
    is free (the crossing point is in the gap).
    """
    for wall in walls:
        dx0, dx1 = p[0] - wall.x, q[0] - wall.x
        if dx0 == 0.0:
            if dx1 == 0.0 and not (wall.gap_lo < q[1] < wall.gap_hi):
                eps = 1e-4 * (wall.gap_hi - wall.gap_lo)
                return np.array([wall.x, np.clip(q[1], wall.gap_lo + eps, wall.gap_hi - eps)]), True
            continue
        if not (dx0 * dx1 < 0.0 or dx1 == 0.0):
            continue  # stays strictly on one side
        y_cross = p[1] + dx0 / (dx0 - dx1) * (q[1] - p[1])
        if wall.gap_lo < y_cross < wall.gap_hi:
            continue
        return np.array([wall.x + np.sign(dx0) * 1e-4, y_cross]), True
    return q, False


class PassageEnv(gym.Env):
    """Point robot through two narrow passages (and around an obstacle in ``high_cov``), guided by KGRL.

    Args:
        scenario: "high_cov" (A) or "low_cov" (B).
        render_mode: None, "rgb_array" or "human" (pygame window).
        demos: optional (M, N, 2) demonstrations to use instead of the scenario's generated ones.
        demo_seed: seed of the generated demonstrations.
        kmp_config: GMM/GMR + LC-NS-KMP hyperparameters.
        scale_model: the exploration scale L (default: constant at the scenario's L0, i.e. KGRL).
        speed: robot speed limit per step (workspace units).
        blocked_limit: consecutive blocked steps that end the episode as a failure.
        start_noise: uniform noise on the start position (0: deterministic start).
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 50}

    def __init__(
        self,
        scenario: str = "high_cov",
        render_mode: str | None = None,
        *,
        demos: np.ndarray | None = None,
        demo_seed: int = 0,
        kmp_config: KMPConfig = KMPConfig(),
        scale_model: ScaleModel | None = None,
        speed: float = 0.01,
        blocked_limit: int = 20,
        start_noise: float = 0.0,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.world = build_world(scenario, demos, demo_seed, kmp_config)
        self.scenario = self.world.scenario
        sm = scale_model if scale_model is not None else ScaleModel(self.scenario.default_scale, dim=2)
        self.mapping = KGRLMapping(self.world.model, sm)
        self.horizon = self.mapping.horizon
        self.render_mode = render_mode
        self.speed = float(speed)
        self.blocked_limit = int(blocked_limit)
        self.start_noise = float(start_noise)
        self.action_space = action_space()
        self.observation_space = observation_space()
        self._correction: np.ndarray | None = None
        self._renderer = None
        self._window = None
        self._reset_state(np.array(self.scenario.start, dtype=np.float64))

    # ------------------------------------------------------------------ state
    def _reset_state(self, start: np.ndarray) -> None:
        self.t = 0
        self.robot = start
        self.desired = start.copy()
        self.blocked_steps = 0
        self.trail = [start.copy()]
        self.last_info: dict = {}
        self._done = False

    def _obs(self) -> np.ndarray:
        t = min(self.t, self.horizon - 1)
        mean = self.mapping.mean(t)
        dev = np.clip(self.robot - mean, -1.0, 1.0)
        return np.array([self.robot[0], self.robot[1], self.mapping.phases[t], dev[0], dev[1]], dtype=np.float32)

    @property
    def phase(self) -> float:
        return float(self.mapping.phases[min(self.t, self.horizon - 1)])

    # ------------------------------------------------------------- human input
    def set_correction(self, p_h: np.ndarray | None) -> None:
        """Hold the desired position at ``p_h`` from the next step on (an intervention); None releases it."""
        if p_h is None:
            self._correction = None
            return
        p_h = np.asarray(p_h, dtype=np.float64).reshape(-1)
        if p_h.shape != (2,) or not np.all(np.isfinite(p_h)):
            raise ValueError(f"a correction is a finite (2,) position, got {p_h!r}")
        self._correction = p_h

    @property
    def intervening(self) -> bool:
        return self._correction is not None

    # ---------------------------------------------------------------- gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        start = np.array(self.scenario.start, dtype=np.float64)
        if self.start_noise > 0:
            start = start + self.np_random.uniform(-self.start_noise, self.start_noise, size=2)
        self._reset_state(start)
        self._correction = None
        if self.render_mode == "human":
            self.render()
        return self._obs(), {"phase": 0.0}

    def step(self, action):
        if self._done:
            raise RuntimeError("step() called after the episode ended: call reset()")
        t = self.t
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be a finite (2,) array, got {action!r}")
        a = np.clip(a, -1.0, 1.0)
        L = self.mapping.scale_at(t, self.robot)
        mean = self.mapping.mean(t)
        info: dict = {"intervened": False, "clipped": False, "projected": False}
        if self._correction is not None:
            m = self.scenario.workspace_margin
            p_h = np.clip(self._correction, m, 1.0 - m)
            info["projected"] = bool(np.any(p_h != self._correction))
            iv = self.mapping.intervene(t, p_h, L)
            desired, xi, stored = p_h, iv.xi, iv.action
            info.update(intervened=True, clipped=iv.clipped, xi_h=iv.xi, raw_action=iv.raw_action)
        else:
            desired, xi = self.mapping.act(t, a, L)
            stored = a
        dp = desired - mean
        r_a = -R_ACTION * float(dp @ dp)

        step = desired - self.robot
        dist = float(np.hypot(*step))
        target = self.robot + (step if dist <= self.speed else step * (self.speed / dist))
        new_pos, blocked = _segment_blocked(self.robot, target, self.scenario.walls)
        self.robot = new_pos
        self.desired = desired
        self.trail.append(new_pos.copy())
        self.blocked_steps = self.blocked_steps + 1 if blocked else 0

        obstacle = self.scenario.obstacle
        in_obstacle = bool(
            obstacle is not None and np.hypot(*(new_pos - np.asarray(obstacle.center))) < obstacle.radius
        )
        r_o = R_OBSTACLE if in_obstacle else 0.0
        r_p = R_PASSAGE if blocked else 0.0
        success = bool(np.hypot(*(new_pos - np.asarray(self.scenario.goal))) <= self.scenario.goal_radius)
        r_T = R_GOAL if success else 0.0
        failed = self.blocked_steps >= self.blocked_limit
        self.t += 1
        terminated = success or failed
        truncated = (not terminated) and self.t >= self.horizon
        reward = r_a + r_o + r_p + r_T
        self._done = terminated or truncated
        info.update(
            r_a=r_a, r_o=r_o, r_p=r_p, r_T=r_T, success=success, failure=failed, blocked=blocked,
            in_obstacle=in_obstacle, action=np.asarray(stored, dtype=np.float32), xi=xi, scale=L,
            desired=desired, phase=float(self.mapping.phases[t]), t=t,
            constraints_active=self.mapping.model.step_info.active_rows if not info["intervened"] else 0,
        )
        self.last_info = info
        if self.render_mode == "human":
            self.render()
        return self._obs(), float(reward), terminated, truncated, info

    # --------------------------------------------------------------- rendering
    def frame_state(self, text: list[str] | None = None):
        from common.render import FrameState

        return FrameState(
            robot=self.robot.copy(),
            desired=self.desired.copy(),
            phase=self.phase,
            trail=np.array(self.trail),
            band=self.mapping.band() if self.mapping.scale_table is not None else None,
            human_active=self._correction is not None,
            correction=None if self._correction is None else self._correction.copy(),
            text=text if text is not None else [
                f"{self.scenario.name}  t={self.t:3d}/{self.horizon}  s={self.phase:.2f}",
                "human: " + ("intervening" if self._correction is not None else "-"),
            ],
        )

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode")
            return None
        from common.render import HumanWindow, SceneRenderer

        if self._renderer is None:
            self._renderer = SceneRenderer(self.scenario, self.world.demos, np.asarray(self.mapping.model.grid_mean))
        state = self.frame_state()
        if self.render_mode == "rgb_array":
            return self._renderer.render_rgb(state)
        if self._window is None:
            self._window = HumanWindow(self._renderer)
        self._window.show(state, fps=self.metadata["render_fps"])
        return None

    def close(self) -> None:
        if self._window is not None:
            self._window.close()
            self._window = None


gym.register(id=ENV_ID, entry_point="common.env:PassageEnv", disable_env_checker=False)
