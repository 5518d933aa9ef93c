"""The paper's 2-D passage world (Section IV, Fig. 3) as a task of the task API: ``--task passage:high_cov``.

The task's environment, :class:`PassageRobot`, is the world without the KGRL mapping: its action is the desired
position P_t, a point robot moves toward it at most ``speed`` per step and cannot cross a wall except through its
gap. Its reward is r_o + r_p + r_T of eq. 7 (r_o = -10 inside the obstacle, r_p = -10 while pressed against a
wall, r_T = +200 on reaching the goal); :class:`~khgrl.common.tasks.kgrl_env.KGRLEnv` adds r_a. Episode end: success
(terminated) at the goal; failure (terminated) when blocked for ``blocked_limit`` consecutive steps.

Observation of the task environment (float64, 2): the robot position (x, y); the policy sees it with the phase
and the deviation from the KMP mean (5 values, as in the paper's runs).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from khgrl.common.kmp.fit import KMPConfig
from khgrl.common.tasks.api import Cuboid, Point, Sphere, Task, View
from khgrl.common.tasks.passage.scenarios import Scenario, get_scenario, make_demos

__all__ = ["PassageRobot", "PassageGuide", "make_task", "segment_blocked", "R_OBSTACLE", "R_PASSAGE", "R_GOAL",
           "REWARD_BOUND", "OBS_BOUND"]

R_OBSTACLE = -10.0
R_PASSAGE = -10.0
R_GOAL = 200.0
REWARD_BOUND = R_GOAL - R_OBSTACLE - R_PASSAGE  # |r_o + r_p + r_T| <= 220 (the learner adds the action cost)
OBS_BOUND = 2.0  # the environment's observation is a position in the unit square


def segment_blocked(p: np.ndarray, q: np.ndarray, walls) -> tuple[np.ndarray, bool]:
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


class PassageRobot(gym.Env):
    """The passage world's robot: action = desired position P_t (2,), observation = robot position (2,).

    :param scenario: the world's geometry.
    :param speed: robot speed limit per step (workspace units).
    :param blocked_limit: consecutive blocked steps that end the episode as a failure.
    :param start_noise: uniform noise on the start position (0: deterministic start).
    """

    metadata = {"render_modes": []}

    def __init__(self, scenario: Scenario, speed: float = 0.01, blocked_limit: int = 20,
                 start_noise: float = 0.0) -> None:
        self.scenario = scenario
        self.speed = float(speed)
        self.blocked_limit = int(blocked_limit)
        self.start_noise = float(start_noise)
        self.observation_space = spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float64)
        self.action_space = spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float64)
        self.robot = np.array(scenario.start, dtype=np.float64)
        self.blocked_steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        start = np.array(self.scenario.start, dtype=np.float64)
        if self.start_noise > 0:
            start = start + self.np_random.uniform(-self.start_noise, self.start_noise, size=2)
        self.robot = start
        self.blocked_steps = 0
        return self.robot.copy(), {}

    def step(self, action):
        desired = np.asarray(action, dtype=np.float64)
        step = desired - self.robot
        dist = float(np.hypot(*step))
        target = self.robot + (step if dist <= self.speed else step * (self.speed / dist))
        new_pos, blocked = segment_blocked(self.robot, target, self.scenario.walls)
        self.robot = new_pos
        self.blocked_steps = self.blocked_steps + 1 if blocked else 0
        obstacle = self.scenario.obstacle
        in_obstacle = bool(
            obstacle is not None and np.hypot(*(new_pos - np.asarray(obstacle.center))) < obstacle.radius)
        r_o = R_OBSTACLE if in_obstacle else 0.0
        r_p = R_PASSAGE if blocked else 0.0
        success = bool(np.hypot(*(new_pos - np.asarray(self.scenario.goal))) <= self.scenario.goal_radius)
        r_T = R_GOAL if success else 0.0
        failed = self.blocked_steps >= self.blocked_limit
        info = dict(r_o=r_o, r_p=r_p, r_T=r_T, success=success, failure=failed, blocked=blocked,
                    in_obstacle=in_obstacle)
        return self.robot.copy(), r_o + r_p + r_T, success or failed, False, info


class PassageGuide:
    """The scripted human of the passage world: within the scenario's ``human_window`` (in workspace x) it
    sets P_h on the safe path through the gaps (``human_waypoints``) at the x the KMP mean has reached."""

    def __init__(self, scenario: Scenario, window: tuple[float, float] | None = None) -> None:
        if not scenario.human_waypoints:
            raise ValueError(f"scenario {scenario.name} has no safe path for a scripted human")
        way = np.asarray(scenario.human_waypoints, dtype=np.float64)
        if np.any(np.diff(way[:, 0]) <= 0):
            raise ValueError("human waypoints must increase in x")
        self.way = way
        self.window = window if window is not None else scenario.human_window

    def path_y(self, x: float) -> float:
        """The safe path's y at workspace x (piecewise linear through the waypoints)."""
        return float(np.interp(x, self.way[:, 0], self.way[:, 1]))

    def __call__(self, mean: np.ndarray) -> np.ndarray | None:
        x = float(mean[0])
        if not (self.window[0] <= x <= self.window[1]):
            return None
        return np.array([x, self.path_y(x)])

    @property
    def takeover(self) -> PassageTakeover:
        """The same human taking over the robot (``--method hil-serl``) instead of correcting the KMP's P_t."""
        return PassageTakeover(self)


class PassageTakeover:
    """The passage world's scripted human when it takes over (HIL-SERL): it helps in the same steps as
    :class:`PassageGuide` (while the KMP mean is in the window), but steers the robot from where it is -- the
    policy may have taken it anywhere -- first onto the safe path at the robot's x, then along it
    (``LOOKAHEAD`` ahead). Aiming at the path point of the mean's x instead would cut across the walls."""

    LOOKAHEAD = 0.05  # workspace units ahead along the path, once on it
    ON_PATH = 0.02  # |y - path| within this: on the path

    def __init__(self, guide: PassageGuide) -> None:
        self.guide = guide

    def __call__(self, mean: np.ndarray, position: np.ndarray) -> np.ndarray | None:
        if self.guide(mean) is None:
            return None
        x, y = float(position[0]), float(position[1])
        on_path = self.guide.path_y(x)
        if abs(y - on_path) > self.ON_PATH:
            return np.array([x, on_path])
        ahead = x + self.LOOKAHEAD
        return np.array([ahead, self.guide.path_y(ahead)])


def view(sc: Scenario) -> View:
    """Walls as thin boxes (one above and one below each gap), the obstacle, start and goal."""
    shapes: list = []
    for k, w in enumerate(sc.walls, 1):
        shapes += [Cuboid(f"wall{k}-low", (w.x - 0.004, 0.0), (w.x + 0.004, w.gap_lo)),
                   Cuboid(f"wall{k}-high", (w.x - 0.004, w.gap_hi), (w.x + 0.004, 1.0))]
    if sc.obstacle is not None:
        shapes.append(Sphere("obstacle", tuple(sc.obstacle.center), sc.obstacle.radius))
    shapes += [Point("start", tuple(sc.start)), Point("goal", tuple(sc.goal))]
    return View(axes=(0, 1), names=("x", "y"), shapes=tuple(shapes))


def make_task(scenario: str = "high_cov", *, demos: np.ndarray | None = None, demo_seed: int = 0,
              kmp_config: KMPConfig = KMPConfig(), speed: float = 0.01, blocked_limit: int = 20,
              start_noise: float = 0.0) -> Task:
    """The passage world's task for ``scenario`` ("high_cov" (A) or "low_cov" (B)).

    :param scenario: the scenario name.
    :param demos: (M, N, 2) demonstrations instead of the scenario's seeded ones.
    :param demo_seed: seed of the generated demonstrations.
    :param kmp_config: GMM/GMR + LC-NS-KMP settings.
    :param speed: robot speed limit per step.
    :param blocked_limit: consecutive blocked steps that fail the episode.
    :param start_noise: uniform noise on the start position.
    """
    sc = get_scenario(scenario)
    m = sc.workspace_margin
    return Task(
        name=f"passage-{sc.name}", make_env=lambda seed: PassageRobot(sc, speed, blocked_limit, start_noise),
        demos=make_demos(sc, seed=demo_seed) if demos is None else demos, workspace=((m, m), (1 - m, 1 - m)),
        kmp=kmp_config, default_scale=sc.default_scale, learn_scale=sc.learn_scale, action_cost=10.0,
        position=lambda obs: obs, scripted_human=PassageGuide(sc) if sc.human_waypoints else None, view=view(sc),
        reward_bound=REWARD_BOUND, obs_bound=OBS_BOUND)
