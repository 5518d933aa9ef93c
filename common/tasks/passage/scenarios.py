"""The 2-D passage world's geometry and its seeded demonstrations (paper Section IV, Fig. 3).

A point robot goes from ``start`` (left) to ``goal`` (right) in the unit square. Two vertical walls
each leave one narrow gap (the passages); scenario A adds a circular obstacle. Nine 400-step
demonstrations were recorded *before* the walls and the obstacle were placed (the paper's "the environment
changed after the demonstrations"), so the demonstrations' mean does not pass the gaps: RL has to learn the
deviation, and the deviation it can reach is bounded by the demonstrations' spread through the soft
null-space projector (math.md §4). The spread is therefore designed per scenario:

* ``high_cov`` (A): demonstrations fan out widely over the middle of the task, where both passages
  and the obstacle lie on or near the mean: with L = 20 exploration reaches far enough to pass and to
  collide (human corrections there need small actions).
* ``low_cov`` (B): demonstrations fan out at the first wall (gap on the mean) but agree closely around
  the second wall, whose gap is off the mean: the deviation reachable with L = 15 there is a few
  thousandths of the distance to the gap, so KGRL cannot pass; a human correction maps to an action of
  magnitude ~1e3-1e4 and the learned L must grow accordingly.

Coordinates are workspace units ([0, 1]^2); time is the normalised phase s = t / (T - 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Wall", "Obstacle", "Scenario", "SCENARIOS", "get_scenario", "make_demos"]


@dataclass(frozen=True)
class Wall:
    """A vertical wall at ``x`` spanning y in [0, 1] except the open gap (gap_lo, gap_hi)."""

    x: float
    gap_lo: float
    gap_hi: float

    @property
    def gap_center(self) -> float:
        return 0.5 * (self.gap_lo + self.gap_hi)


@dataclass(frozen=True)
class Obstacle:
    """A circular obstacle: entering it costs (eq. 8); it does not block motion."""

    center: tuple[float, float]
    radius: float


@dataclass(frozen=True)
class Scenario:
    """Geometry, default exploration scale and demonstration design of one passage world."""

    name: str
    start: tuple[float, float]
    goal: tuple[float, float]
    walls: tuple[Wall, ...]
    obstacle: Obstacle | None
    default_scale: float  # L (per dimension), paper: 20 in A, 15 in B
    # KhGRL refits L from the human here (paper: B only; in A "the exploration noise ... is kept equal")
    learn_scale: bool
    # demonstration spread (half-width of the fan in y) as (phase, half_width) knots, linearly interpolated
    spread_knots: tuple[tuple[float, float], ...]
    arrive_phase: float = 0.92  # demonstrations reach the goal at this phase and dwell there
    goal_radius: float = 0.03
    workspace_margin: float = 0.02  # hard constraints keep P_t in [margin, 1 - margin]^2
    human_waypoints: tuple[tuple[float, float], ...] = field(default=())  # a safe path through the gaps
    human_window: tuple[float, float] = (0.0, 1.0)  # x-range of the path where a human helps


SCENARIOS: dict[str, Scenario] = {
    "high_cov": Scenario(
        name="high_cov",
        start=(0.08, 0.5),
        goal=(0.92, 0.5),
        walls=(Wall(0.32, 0.57, 0.64), Wall(0.68, 0.57, 0.64)),
        obstacle=Obstacle(center=(0.5, 0.5), radius=0.07),
        default_scale=20.0,
        learn_scale=False,
        spread_knots=((0.0, 0.0), (0.12, 0.02), (0.25, 0.16), (0.75, 0.16), (0.88, 0.02), (1.0, 0.0)),
        human_waypoints=((0.08, 0.5), (0.26, 0.605), (0.5, 0.625), (0.74, 0.605), (0.92, 0.5)),
        human_window=(0.2, 0.8),
    ),
    "low_cov": Scenario(
        name="low_cov",
        start=(0.08, 0.5),
        goal=(0.92, 0.5),
        walls=(Wall(0.32, 0.465, 0.535), Wall(0.68, 0.555, 0.615)),
        obstacle=None,
        default_scale=15.0,
        learn_scale=True,
        spread_knots=((0.0, 0.0), (0.1, 0.02), (0.22, 0.12), (0.4, 0.12), (0.5, 0.006), (0.8, 0.006), (0.9, 0.002),
                      (1.0, 0.0)),
        human_waypoints=((0.08, 0.5), (0.32, 0.5), (0.56, 0.585), (0.76, 0.585), (0.92, 0.5)),
        human_window=(0.5, 0.8),
    ),
}


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}") from None


def _min_jerk(u: np.ndarray) -> np.ndarray:
    return 10 * u**3 - 15 * u**4 + 6 * u**5


def make_demos(scenario: Scenario | str, n_demos: int = 9, n_steps: int = 400, seed: int = 0) -> np.ndarray:
    """Seeded demonstrations (M, N, 2): a fan of smooth start->goal paths whose half-width follows the
    scenario's spread profile, with small per-demo timing and shape noise.
    """
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    if n_demos < 2 or n_steps < 10:
        raise ValueError(f"need n_demos >= 2 and n_steps >= 10, got {n_demos}, {n_steps}")
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n_steps)
    knots = np.array(sc.spread_knots)
    offsets = np.linspace(-1.0, 1.0, n_demos)
    rng.shuffle(offsets)
    (x0, y0), (x1, y1) = sc.start, sc.goal
    demos = np.empty((n_demos, n_steps, 2))
    for m in range(n_demos):
        arrive = sc.arrive_phase * (1.0 + 0.02 * rng.uniform(-1, 1))
        u = np.clip(s / arrive, 0.0, 1.0)
        progress = _min_jerk(u)
        x = x0 + (x1 - x0) * progress
        # the spread is a function of the path position, so a demo that is early or late still fans out at the
        # same place in the workspace
        half_width = np.interp(progress, knots[:, 0], knots[:, 1])
        wobble = 0.15 * np.sin(np.pi * progress * rng.integers(1, 3) + rng.uniform(0, 2 * np.pi))
        y = y0 + (y1 - y0) * progress + half_width * (offsets[m] + wobble * abs(offsets[m]))
        demos[m, :, 0] = x
        demos[m, :, 1] = y
    return demos
