"""LeRobot's gym-hil Panda pick-cube behind the KGRL mapping, commanded by desired position.

:class:`PandaPosition` wraps ``PandaPickCubeGymEnv`` (``gym_hil/PandaPickCubeBase-v0``, the simulated task LeRobot's
HIL-SERL is tuned on; the ``gym-hil`` package from the package index, not copied) through gym-hil's own
``EEActionWrapper`` with its default step (2.5 cm per control step at |action| = 1, what ``gym_hil/PandaPickCube-v0``
uses). gym-hil's base action is Box(7) in [-1, 1]: a displacement of the controller's target (a MuJoCo mocap body
that its operational-space controller pulls the gripper's pinch site to, clipped to the cartesian bounds
[0.2, 0.6] x [-0.3, 0.3] x [0, 0.5] m), three orientation entries it ignores, and a gripper increment (+1 closes the
Robotiq 2F-85 fully in one step, -1 opens it). Control runs at 10 Hz (``control_dt`` 0.1 s, 50 physics steps of
2 ms each). The KGRL mapping commands a desired gripper position P_t in R^3 (metres, gym-hil's world frame); the
adapter moves the target toward it:

    a_xyz = clip((P_t - target) / EE_STEP, -1, 1),   a_grip = 2 if gripper(phase) is closed else 0

(``EEActionWrapper``'s gripper action is in [0, 2]: 0 opens, 2 closes.) Commanding the target rather than the
measured pinch site keeps the target from winding up while the gripper is held back (pressing on the table, a
grasped cube): the target reaches P_t and stays. The gripper is scheduled by phase, as for Fetch
(:class:`~khgrl.common.tasks.fetch.arm.GripperSchedule`).

The cube: gym-hil's reset places it at (0.5, 0) (``random_block_position=False``, the registered default) or, with
``random_block_position=True``, draws it with numpy's *global* RNG (``np.random.uniform``), which the reset seed
does not reach. So this wrapper places it itself after gym-hil's reset, uniformly in ``region`` (default gym-hil's
own sampling bounds, x in [0.3, 0.5], y in [-0.15, 0.15] m) from its own ``np_random``, seeded by ``reset(seed=...)``
(Gymnasium's rule): the same seed gives the same scene.

Observation (float64, 21; each entry clipped to the bounds stated): gym-hil's ``agent_pos`` (18) -- joint angles
(7, rad, the model's joint ranges), joint velocities (7, rad/s, [-10, 10]), the gripper command scaled to [0, 1]
(gym-hil gives 0..255), the pinch site's position (3, m, [-1, 1]) -- and ``environment_state``, the cube's position
(3, m, [-1, 1]). Reward: gym-hil's sparse reward (1 once the cube is 10 cm above where it started, else 0);
``info["succeed"]`` is gym-hil's success. Episode end: gym-hil's termination (success, or the cube pushed more
than 5 cm out of its sampling bounds); truncation after ``horizon`` steps.

Rendering needs an OpenGL context even headless (gym-hil's constructor makes a ``mujoco.Renderer``): this module
sets ``MUJOCO_GL=egl`` unless it is set, before MuJoCo is first imported.
"""

from __future__ import annotations

import atexit
import os
import sys
import warnings
import weakref

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from khgrl.common.tasks.fetch.arm import CLOSED, GripperSchedule

__all__ = ["PandaPosition", "EE_STEP", "REGION", "BOUNDS", "TCP", "CUBE", "OBS_DIM", "panda_command"]

if "mujoco" not in sys.modules and "DISPLAY" not in os.environ:
    os.environ.setdefault("MUJOCO_GL", "egl")  # gym-hil renders at construction; no display here

EE_STEP = 0.025  # metres per control step at |action| = 1 (gym-hil's DEFAULT_EE_STEP_SIZE)
BOUNDS = ((0.2, -0.3, 0.0), (0.6, 0.3, 0.5))  # gym-hil's _CARTESIAN_BOUNDS: where its target can go
REGION = ((0.3, -0.15), (0.5, 0.15))  # gym-hil's _SAMPLING_BOUNDS: where the cube is placed
OBS_DIM = 21
GRIP = 14  # index of the gripper command (0..1) in the observation
TCP = slice(15, 18)  # the pinch site's position
CUBE = slice(18, 21)  # the cube's position
QVEL_BOUND = 10.0  # rad/s
MAX_GRIPPER_COMMAND = 255.0
PUSH_FORCE, PUSH_NEAR = 30.0, 0.02  # the scripted physical human's push (N), tapered within this distance (m)


def panda_command(p_t: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The displacement part of ``EEActionWrapper``'s action that moves gym-hil's target toward P_t (clipped to
    [-1, 1]^3: at most ``EE_STEP`` per step and axis)."""
    return np.clip((np.asarray(p_t, np.float64) - np.asarray(target, np.float64)) / EE_STEP, -1.0, 1.0)


def _headless_gl() -> None:
    """Without a display, make MuJoCo's renderer use EGL even if MuJoCo was imported before this module (e.g. by
    ``import gym_hil``) without ``MUJOCO_GL``, which picked GLFW (it needs a display): ``mujoco.Renderer`` reads
    ``mujoco.gl_context.GLContext`` when it is made, so that name is pointed at EGL's context (what
    ``MUJOCO_GL=egl`` selects at import). With a display, or another backend chosen, nothing changes."""
    if "DISPLAY" in os.environ:
        return
    from mujoco import gl_context

    ctx = getattr(gl_context, "GLContext", None)
    if ctx is not None and ctx.__module__.startswith("mujoco.glfw"):
        from mujoco.egl import GLContext

        gl_context.GLContext = GLContext


def _close_at_exit(ref: weakref.ref) -> None:
    """Close the environment if it is still alive (its renderers' EGL contexts)."""
    env = ref()
    if env is not None:
        env.close()


def _make_base():
    """gym-hil's PandaPickCube base environment wrapped in its own ``EEActionWrapper`` (imported here, so that
    the task can be described without constructing MuJoCo)."""
    _headless_gl()
    from gym_hil.envs import PandaPickCubeGymEnv
    from gym_hil.wrappers.hil_wrappers import DEFAULT_EE_STEP_SIZE, EEActionWrapper

    if set(DEFAULT_EE_STEP_SIZE.values()) != {EE_STEP}:
        raise RuntimeError(f"gym-hil's EE step is {DEFAULT_EE_STEP_SIZE}, this adapter assumes {EE_STEP} m")
    base = PandaPickCubeGymEnv(random_block_position=False)
    with warnings.catch_warnings():  # its float32 Box from float64 bounds (0, 2, +-1: exact in float32)
        warnings.filterwarnings("ignore", message=".*precision lowered by casting to float32.*")
        return base, EEActionWrapper(base, ee_action_step_size=DEFAULT_EE_STEP_SIZE, use_gripper=True)


class PandaPosition(gym.Env):
    """gym-hil's Panda pick-cube with the desired gripper position as its action (see the module docstring).

    :param horizon: N, steps per episode (the KMP grid's length).
    :param workspace: (low, high) of the commanded position (the action space; default gym-hil's bounds).
    :param gripper: the gripper command by phase.
    :param region: ((x_lo, y_lo), (x_hi, y_hi)) where the cube is placed at reset (uniform, from the reset seed);
        None: where gym-hil puts it, (0.5, 0).
    """

    metadata = {"render_modes": []}

    def __init__(self, horizon: int = 60, workspace: tuple = BOUNDS, gripper: GripperSchedule = GripperSchedule(),
                 region: tuple | None = REGION) -> None:
        self.base, self.env = _make_base()
        # free gym-hil's renderer at exit before MuJoCo's EGL display is terminated (MuJoCo registers that at its
        # first context, made just now: atexit runs the later registration first); else its __del__ prints errors
        atexit.register(_close_at_exit, weakref.ref(self))
        self.horizon = int(horizon)
        self.gripper = gripper
        self.region = None if region is None else tuple(np.asarray(r, np.float64) for r in region)
        low, high = (np.asarray(w, np.float64) for w in workspace)
        self.action_space = spaces.Box(low, high, dtype=np.float64)
        jr = np.asarray(self.base.model.jnt_range[self.base._panda_dof_ids], np.float64)
        self._low = np.concatenate([jr[:, 0], -np.full(7, QVEL_BOUND), [0.0], -np.ones(6)])
        self._high = np.concatenate([jr[:, 1], np.full(7, QVEL_BOUND), [1.0], np.ones(6)])
        self.observation_space = spaces.Box(self._low, self._high, dtype=np.float64)
        self.t = 0
        self._obs: dict | None = None
        self._camera = None

    @property
    def target(self) -> np.ndarray:
        """gym-hil's controller target (the mocap body) now."""
        return np.asarray(self.base.data.mocap_pos[0], np.float64).copy()

    @property
    def gripper_closed(self) -> bool:
        """Whether the gripper is commanded closed (what a real gripper's status reports; the task's ``contact``:
        closed on the cube, or on nothing)."""
        return bool(self._obs is not None and self._obs["agent_pos"][GRIP] / MAX_GRIPPER_COMMAND > 0.5)

    @property
    def gripper_pos(self) -> np.ndarray:
        """The pinch site's position now (metres)."""
        return np.asarray(self._obs["agent_pos"][15:18], np.float64)

    @property
    def cube_pos(self) -> np.ndarray:
        return np.asarray(self._obs["environment_state"], np.float64)

    def _flat(self) -> np.ndarray:
        flat = np.concatenate([self._obs["agent_pos"], self._obs["environment_state"]]).astype(np.float64)
        flat[GRIP] /= MAX_GRIPPER_COMMAND
        return np.clip(flat, self._low, self._high)

    def _place(self) -> None:
        """Put the cube at a uniform place in ``region`` drawn from ``np_random`` (after gym-hil's own reset)."""
        import mujoco

        base = self.base
        xy = self.np_random.uniform(self.region[0], self.region[1])
        base.data.jnt("block").qpos[:3] = (xy[0], xy[1], base._block_z)
        mujoco.mj_forward(base.model, base.data)
        base._z_init = float(base.data.sensor("block_pos").data[2])  # gym-hil's success height follows
        base._z_success = base._z_init + 0.1
        self._obs = base._compute_observation()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.push(None)  # (a push does not outlive its episode)
        self._obs, _ = self.env.reset(seed=seed, options=options)
        if self.region is not None:
            self._place()
        self.t = 0
        return self._flat(), {}

    def step(self, action):
        phase = min(self.t / max(self.horizon - 1, 1), 1.0)
        grip = 2.0 if self.gripper(phase) == CLOSED else 0.0
        a = np.concatenate([panda_command(action, self.target), [grip]])
        self._obs, reward, terminated, truncated, info = self.env.step(a.astype(np.float32))
        self.t += 1
        truncated = bool(truncated) or self.t >= self.horizon
        return self._flat(), float(reward), bool(terminated), truncated, {"succeed": bool(info.get("succeed"))}

    def push(self, p_h: np.ndarray | None) -> None:
        """The scripted physical human: a force on the gripper's base body towards ``p_h`` during the next step(s),
        ``PUSH_FORCE`` N, in proportion within ``PUSH_NEAR`` of the pinch site (MuJoCo's ``xfrc_applied``; gym-hil's
        operational-space controller yields to it: about 2 cm per 20 N held); None lets go.

        :param p_h: where the hand pushes the gripper towards (None: no force).
        """
        import mujoco

        base = self.base
        body = mujoco.mj_name2id(base.model, mujoco.mjtObj.mjOBJ_BODY, "base")
        force = np.zeros(3)
        if p_h is not None:  # a firm hand: PUSH_FORCE towards p_h, less only within PUSH_NEAR of it
            gap = np.asarray(p_h, np.float64) - self.gripper_pos
            dist = float(np.linalg.norm(gap))
            force = PUSH_FORCE * gap / max(dist, PUSH_NEAR) if dist > 0 else force
        base.data.xfrc_applied[body, :3] = force
        base.data.xfrc_applied[body, 3:] = 0.0

    def camera_frame(self, size: int = 360) -> np.ndarray:
        """gym-hil's front camera now, (size, size, 3) uint8 (offscreen; ``khgrl eval --gif`` puts it beside the
        task's views).

        :param size: width and height in pixels.
        """
        import mujoco

        if self._camera is None or self._camera.width != size:
            if self._camera is not None:
                self._camera.close()
            vis = self.base.model.vis.global_
            vis.offwidth, vis.offheight = max(vis.offwidth, size), max(vis.offheight, size)
            self._camera = mujoco.Renderer(self.base.model, height=size, width=size)
        cam = mujoco.mj_name2id(self.base.model, mujoco.mjtObj.mjOBJ_CAMERA, "front")
        self._camera.update_scene(self.base.data, camera=cam)
        return np.asarray(self._camera.render(), dtype=np.uint8)

    def close(self) -> None:
        if self._camera is not None:
            self._camera.close()
            self._camera = None
        self.env.close()
