"""A third-party MuJoCo arm behind the KGRL mapping: gymnasium-robotics' Fetch, commanded by desired position.

:class:`FetchPosition` wraps ``FetchPickAndPlace-v4`` (or ``FetchPush-v4``) from the ``gymnasium-robotics``
package (installed from the package index, not copied). The KGRL mapping commands a desired end-effector
position P_t in R^3 (metres, the environment's world frame); the adapter turns it into Fetch's own action, an
end-effector displacement in [-1, 1]^3 (times 5 cm per step, Fetch's ``pos_ctrl`` scale) plus a gripper command:

    a_xyz = clip((P_t - gripper position) / MAX_STEP, -1, 1),   a_grip = gripper(phase)

The gripper is scheduled by phase (:class:`GripperSchedule`: open, closed over the grasp-to-release part of the
task, open) rather than learned as a fourth KMP output: a pick-and-place grasp is a discrete event at a phase
the demonstrations agree on, and exploring a continuous gripper command in its null space would only add
failed grasps. Unobstructed, the gripper reaches a P_t 10 cm away to within 1.5 cm in 3 steps and 1 mm in 5
(tests/unit/test_fetch_arm.py).

Observation (float64, 28): Fetch's ``observation`` (gripper position, object position, relative position,
gripper fingers, object rotation and velocities, ...; 25) and the ``desired_goal`` (3). Reward: Fetch's sparse
reward (0 at the goal, -1 elsewhere) per step; ``info["success"]`` is Fetch's ``is_success``. Episode end:
truncation after ``horizon`` steps (Fetch has no termination).
"""

from __future__ import annotations

import contextlib
import io
import sys
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces

__all__ = ["FetchPosition", "GripperSchedule", "MAX_STEP", "fetch_command", "import_robotics", "OBS_BOUND",
           "REWARD_BOUND"]

MAX_STEP = 0.05  # metres per step at |action| = 1 (Fetch's pos_ctrl scale)
OPEN, CLOSED = 1.0, -1.0
OBS_BOUND = 10.0  # every observation is clipped to +-10 (the task states it as its obs_bound)
REWARD_BOUND = 1.0  # Fetch's sparse reward: 0 at the goal, -1 elsewhere (the task's reward_bound)


def import_robotics():
    """``gymnasium_robotics``, imported without the notice it prints on stderr at import (a Farama notification
    about the AdroitHand environments' reward versions, nothing to do with Fetch). Exactly that text is dropped;
    anything else printed during the import (a warning, an error) is passed on to stderr."""
    if "gymnasium_robotics" in sys.modules:
        return sys.modules["gymnasium_robotics"]
    captured = io.StringIO()
    with contextlib.redirect_stderr(captured):
        import gymnasium_robotics
    text = captured.getvalue()
    try:
        from farama_notifications import notifications

        notice = notifications.get("gymnasium_robotics", {}).get(gymnasium_robotics.__version__)
    except Exception:  # noqa: BLE001 - no notifications package: nothing to drop
        notice = None
    if notice:
        text = text.replace(f"{notice}\n", "", 1)
    if text:
        sys.stderr.write(text)
    return gymnasium_robotics


@dataclass(frozen=True)
class GripperSchedule:
    """Gripper command by phase: open before ``close_at``, closed until ``open_at``, then open again.

    :param close_at: phase at which the gripper closes (the grasp).
    :param open_at: phase at which it opens (the release; 1.0 or more: never).
    """

    close_at: float = 0.35
    open_at: float = 1.1

    def __call__(self, phase: float) -> float:
        return CLOSED if self.close_at <= phase < self.open_at else OPEN


def fetch_command(p_t: np.ndarray, gripper_pos: np.ndarray) -> np.ndarray:
    """The displacement part of Fetch's action that moves the gripper toward P_t (clipped to [-1, 1]^3)."""
    return np.clip((np.asarray(p_t, np.float64) - np.asarray(gripper_pos, np.float64)) / MAX_STEP, -1.0, 1.0)


class FetchPosition(gym.Env):
    """Fetch with the desired gripper position as its action (see the module docstring).

    :param env_id: a gymnasium-robotics Fetch id with a 4-D action (``FetchPickAndPlace-v4``, ``FetchPush-v4``).
    :param horizon: N, steps per episode (the KMP grid's length).
    :param workspace: (low, high) of the commanded position (the action space).
    :param gripper: the gripper command by phase.
    :param object_xy: where the object is placed at reset (None: Fetch's own random placement).
    :param goal: the target position (None: Fetch's own random goal).
    :param env_kwargs: further keyword arguments of ``gym.make(env_id, ...)`` (e.g. another scene's model file).
    """

    metadata = {"render_modes": []}

    def __init__(self, env_id: str = "FetchPickAndPlace-v4", horizon: int = 100,
                 workspace: tuple = ((1.05, 0.4, 0.42), (1.55, 1.1, 0.9)), gripper: GripperSchedule = GripperSchedule(),
                 object_xy: tuple[float, float] | None = None, goal: tuple[float, float, float] | None = None,
                 env_kwargs: dict | None = None) -> None:
        gym.register_envs(import_robotics())
        self.env = gym.make(env_id, max_episode_steps=horizon, **(env_kwargs or {}))
        self.horizon = int(horizon)
        self.gripper = gripper
        self.object_xy = None if object_xy is None else np.asarray(object_xy, np.float64)
        self.goal = None if goal is None else np.asarray(goal, np.float64)
        low, high = (np.asarray(w, np.float64) for w in workspace)
        self.action_space = spaces.Box(low, high, dtype=np.float64)
        # positions are metres within ~2 m of the origin, velocities are per control step: |value| < 10 always
        self.observation_space = spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(28,), dtype=np.float64)
        self.t = 0
        self._obs: dict | None = None
        self._camera = None

    @property
    def gripper_pos(self) -> np.ndarray:
        """The end effector's position now (metres)."""
        return np.asarray(self._obs["observation"][:3], np.float64)

    @property
    def object_pos(self) -> np.ndarray:
        return np.asarray(self._obs["observation"][3:6], np.float64)

    def _flat(self) -> np.ndarray:
        flat = np.concatenate([self._obs["observation"], self._obs["desired_goal"]]).astype(np.float64)
        return np.clip(flat, -OBS_BOUND, OBS_BOUND)

    def _place(self) -> None:
        """Move the object to ``object_xy`` and the goal to ``goal`` (after Fetch's own reset)."""
        base = self.env.unwrapped
        if self.object_xy is not None:
            qpos = base._utils.get_joint_qpos(base.model, base.data, "object0:joint").copy()
            qpos[:2] = self.object_xy
            base._utils.set_joint_qpos(base.model, base.data, "object0:joint", qpos)
            import mujoco

            mujoco.mj_forward(base.model, base.data)
        if self.goal is not None:
            base.goal = self.goal.copy()
        self._obs = base._get_obs()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._obs, _ = self.env.reset(seed=seed, options=options)
        self._place()
        self.t = 0
        return self._flat(), {}

    def step(self, action):
        phase = min(self.t / max(self.horizon - 1, 1), 1.0)
        a = np.concatenate([fetch_command(action, self.gripper_pos), [self.gripper(phase)]])
        self._obs, reward, terminated, truncated, info = self.env.step(a.astype(np.float32))
        self.t += 1
        success = bool(info.get("is_success", 0.0) > 0.5)
        return self._flat(), float(reward), bool(terminated), bool(truncated), {"success": success}

    def camera_frame(self, size: int = 360) -> np.ndarray:
        """What MuJoCo's default camera sees now, (size, size, 3) uint8 (offscreen: needs ``MUJOCO_GL=egl`` or
        ``osmesa`` without a display; ``khgrl eval --gif`` puts it beside the task's views).

        :param size: width and height in pixels.
        """
        if self._camera is None or self._camera.width != size:
            from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer

            base = self.env.unwrapped
            self._camera = MujocoRenderer(base.model, base.data, default_cam_config={
                "distance": 1.6, "azimuth": 150.0, "elevation": -30.0, "lookat": np.array([1.3, 0.75, 0.5])},
                width=size, height=size)
        return np.asarray(self._camera.render("rgb_array"), dtype=np.uint8)

    def close(self) -> None:
        if self._camera is not None:
            self._camera.close()
        self.env.close()
