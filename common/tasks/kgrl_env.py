"""Any task behind the KGRL mapping, as one Gymnasium environment the actor (or single-process SB3) steps.

``KGRLEnv(task)`` wraps the task's environment (:mod:`khgrl.common.tasks.api`). One step at time index t (phase
s = t / (N - 1), N the KMP grid):

1. L_t, the exploration scale in force, is read from the scale model;
2. KGRL (no correction pending): the policy action a in [-1, 1]^O is unscaled, xi = L_t (.) a, and the
   LC-NS-KMP gives the desired position P_t inside the hard constraints (eq. 5);
   KhGRL (a correction P_h pending, :meth:`KGRLEnv.set_correction`): P_h is projected onto the workspace box
   (counted), P_t = P_h, and the stored action is a_h = clip(N_t^-1 (P_h - eta0_t) (/) L_t) (eq. 6);
3. the task's environment is stepped with P_t (or with ``task.command(env, P_t)``);
4. reward r = r_a + the environment's reward, r_a = -``action_cost`` dp^T dp with dp = P_t - eta0_t (eq. 7).

Episode end: the task environment's termination; truncation by the environment or after N steps.

Observation (float32): the environment's observation, the phase s, and the robot's deviation from the KMP
mean at this phase clipped to [-1, 1]^O (the robot: ``task.position(obs)``, or the command last sent). A task with
cameras (``Task.image_keys``): a ``spaces.Dict``, ``"state"`` = the environment's state vector, s and the deviation
(float32), plus each image unchanged (uint8) (:mod:`khgrl.common.tasks.obs_spaces`).

Action: a in [-1, 1]^O (float32), the null-space action of eq. 5; with ``control="delta"`` (the HIL-SERL
baseline, :mod:`khgrl.common.tasks.delta`) a displacement instead: P_t = clip(position + step a) in the workspace
box, no band, reward r = the environment's (no r_a), and a correction is a takeover: a_h = the action towards P_h.

Safety counts in ``info`` for every control: ``violation`` (the commanded P_t violates a hard constraint
G P >= c) and ``workspace_exit`` (the policy asked for a position outside the workspace box). With ``rate_limit``
(:class:`~khgrl.common.tasks.safety.RateLimiter`) the position sent to the task's environment is P_t rate-limited
(``rate_limited``: it differs); the action cost r_a is the mapping's P_t's, the violation count and ``desired``
are of the position sent.

Scenes that change every episode (a task with a :class:`~khgrl.common.tasks.scene.Scene`): at every reset the
placement is read from the first observation (``env.placement``, ``info["scene"]``) and, with ``adapt`` and the
scene's via-points, the LC-NS-KMP is refitted through them (:func:`khgrl.common.kmp.adapt.adapt_model`): the mean,
the projector, the band, eqs. 5-6 and the action cost follow the adapted model for that episode. The exploration
scale L stays a function of the phase: it scales the null-space action about whatever mean the episode has.
:meth:`KGRLEnv.reset_episode` resets episode ``e`` of a run to the scene :func:`~khgrl.common.tasks.scene.scene_seed`
gives.

One module of ~385 lines on purpose: one Gymnasium environment, the KGRL mapping of a task; its reset and step share
the KMP's state.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from khgrl.common.kmp.mapping import KGRLMapping
from khgrl.common.kmp.scale import ScaleModel
from khgrl.common.tasks.adapted import episode_scene
from khgrl.common.tasks.api import Task, TaskError
from khgrl.common.tasks.delta import DeltaControl
from khgrl.common.tasks.motion import measured, reset_path
from khgrl.common.tasks.obs_spaces import camera_layout, policy_obs, policy_space
from khgrl.common.tasks.safety import RateLimiter
from khgrl.common.tasks.scene import scene_seed
from khgrl.common.tasks.world import TaskWorld, build_task_world

__all__ = ["KGRLEnv", "make_inner_env", "CONTROLS"]

CONTROLS = ("kmp", "delta")  # eq. 5 about the KMP mean; delta actions in the workspace (HIL-SERL)
VIOLATION_TOL = 1e-6  # a hard constraint counts as violated by more than this


def make_inner_env(task: Task, seed: int) -> gym.Env:
    """The task's own environment, checked: a 1-D Box observation (a task with cameras: the ``spaces.Dict`` it
    declares, :func:`~khgrl.common.tasks.obs_spaces.camera_layout`); a (O,) Box action unless ``command`` adapts."""
    try:
        env = task.make_env(seed)
    except TaskError:
        raise
    except Exception as exc:  # noqa: BLE001 - the user's factory
        raise TaskError(f"task {task.name!r}: make_env raised {type(exc).__name__}: {exc}") from None
    if not isinstance(env, gym.Env):
        raise TaskError(f"task {task.name!r}: make_env returned {type(env).__name__}, not a gymnasium.Env")
    obs = env.observation_space
    if camera_layout(task, obs) is not None:
        return env
    if not isinstance(obs, spaces.Box) or len(obs.shape) != 1:
        raise TaskError(f"task {task.name!r}: the environment's observation space must be a 1-D Box, got {obs}")
    return env


class KGRLEnv(gym.Env):
    """A task's environment driven through the KGRL mapping (see the module docstring).

    :param task: the task (or ``world``, an already built :class:`~khgrl.common.tasks.world.TaskWorld`).
    :param seed: seed passed to ``task.make_env`` and to the environment's first reset.
    :param scale_model: the exploration scale L (default: constant L0, i.e. KGRL).
    :param render_mode: None or "rgb_array" (the task's views, :mod:`khgrl.common.tasks.render`).
    :param world: a built world (skips fitting; e.g. cached).
    :param inner: the task's environment (default: ``task.make_env(seed)``).
    :param adapt: refit the KMP through the scene's via-points at every reset (tasks with a varying scene).
    :param control: "kmp" (eqs. 5-6, KGRL and KhGRL) or "delta" (the HIL-SERL baseline's delta actions).
    :param rate_limit: ``(max_speed, max_accel)`` in units of the demonstrations' largest step: limit P_t's rate
        (:class:`~khgrl.common.tasks.safety.RateLimiter`; None: no limit).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, task: Task | None = None, *, seed: int = 0, scale_model: ScaleModel | None = None,
                 render_mode: str | None = None, world: TaskWorld | None = None, inner: gym.Env | None = None,
                 adapt: bool = True, control: str = "kmp", rate_limit: tuple[float, float] | None = None) -> None:
        if control not in CONTROLS:
            raise ValueError(f"control must be one of {CONTROLS}, got {control!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.world = world if world is not None else build_task_world(task)
        self.task = self.world.task
        o = self.world.out_dim
        self.inner = inner if inner is not None else make_inner_env(self.task, seed)
        self._check_command_space(o)
        sm = scale_model if scale_model is not None else ScaleModel(self.world.default_scale, dim=o)
        self.mapping = KGRLMapping(self.world.model, sm)
        self.horizon = self.mapping.horizon
        self.render_mode = render_mode
        self.action_space = spaces.Box(-1.0, 1.0, shape=(o,), dtype=np.float32)
        ob = self.inner.observation_space
        self.cameras = camera_layout(self.task, ob)  # None: a vector task
        self.observation_space = policy_space(self.cameras, o) if self.cameras is not None else spaces.Box(
            low=np.concatenate([ob.low.astype(np.float64), [0.0], -np.ones(o)]).astype(np.float32),
            high=np.concatenate([ob.high.astype(np.float64), [1.0], np.ones(o)]).astype(np.float32),
            dtype=np.float32)
        self._inner_seed: int | None = int(seed)
        self.seed_base = int(seed)
        self.scene_seed: int | None = None
        self.via_error, self.max_violation = 0.0, -np.inf
        self.adapt = bool(adapt)
        self.delta = DeltaControl.from_demos(self.world.demos, self.world.low, self.world.high) \
            if control == "delta" else None
        self.limiter = None if rate_limit is None else RateLimiter.from_demos(self.world.demos, *rate_limit,
                                                                               self.world.low, self.world.high)
        self.path_limiter: RateLimiter | None = None  # while the path back to the start runs (motion.reset_path)
        self.placement: dict[str, float] = {}
        self.via_points: list = []  # (grid step, position) of this episode's via-points
        self._correction: np.ndarray | None = None
        self._renderer = None
        self._scene_cache = None
        self._reset_state(np.asarray(self.mapping.mean(0), dtype=np.float64).copy(), None)

    def _check_command_space(self, o: int) -> None:
        if self.task.command is not None:
            return
        act = self.inner.action_space
        if not isinstance(act, spaces.Box) or act.shape != (o,):
            raise TaskError(f"task {self.task.name!r}: the environment's action must be the desired position, a Box "
                            f"of shape ({o},) like the demonstrations, got {act}; or give the task a command adapter")

    # ------------------------------------------------------------------ state
    def _reset_state(self, position: np.ndarray, inner_obs: np.ndarray | None) -> None:
        self.t = 0
        self.position = position
        self.desired = position.copy()
        self.anchor, self.sent_step = position.copy(), np.zeros_like(position)  # the next step starts there, at rest
        self.trail = [position.copy()]
        self._inner_obs = inner_obs
        self._done = False
        if getattr(self, "limiter", None) is not None:
            self.limiter.reset(position)

    def _locate(self, inner_obs: np.ndarray, fallback: np.ndarray) -> np.ndarray:
        if self.task.position is None:
            return np.asarray(fallback, dtype=np.float64).copy()
        p = np.asarray(self.task.position(inner_obs), dtype=np.float64).reshape(-1)
        if p.shape != (self.world.out_dim,) or not np.all(np.isfinite(p)):
            raise TaskError(f"task {self.task.name!r}: position(obs) must give {self.world.out_dim} finite values, "
                            f"got {p}")
        return p

    def _obs(self) -> np.ndarray | dict[str, np.ndarray]:
        t = min(self.t, self.horizon - 1)
        dev = np.clip(self.position - self.mapping.mean(t), -1.0, 1.0)
        if self.cameras is not None:
            return policy_obs(self.cameras, self._inner_obs, float(self.mapping.phases[t]), dev)
        inner = np.asarray(self._inner_obs, dtype=np.float64).reshape(-1)
        return np.concatenate([inner, [self.mapping.phases[t]], dev]).astype(np.float32)

    @property
    def inner_obs(self) -> np.ndarray | None:
        """The task environment's latest observation (None before the first reset)."""
        return self._inner_obs

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
        if p_h.shape != (self.world.out_dim,) or not np.all(np.isfinite(p_h)):
            raise ValueError(f"a correction is a finite ({self.world.out_dim},) position, got {p_h!r}")
        self._correction = p_h

    @property
    def intervening(self) -> bool:
        return self._correction is not None

    @property
    def correction(self) -> np.ndarray | None:
        """The correction P_h held now (None: the policy drives)."""
        return None if self._correction is None else self._correction.copy()

    # ---------------------------------------------------------------- gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        inner_seed = seed if seed is not None else self._inner_seed
        self._inner_seed = None
        inner_obs, info = self.inner.reset(seed=inner_seed, options=options)
        self._new_scene(inner_obs)
        start = np.asarray(self.mapping.mean(0), dtype=np.float64)
        self._reset_state(self._locate(inner_obs, start), inner_obs)
        self._correction = None
        extra = {"scene": dict(self.placement)} if self.task.scene is not None else {}
        return self._obs(), {**info, **extra, "phase": 0.0}

    @property
    def varies(self) -> bool:
        """Whether the task's scene changes every episode."""
        return self.task.scene is not None

    def reset_episode(self, episode: int):
        """Reset for episode ``episode`` (1-based) of the run: a varying scene is drawn from
        ``scene_seed(seed, episode)``; a fixed scene is reset as :meth:`reset` without a seed does.

        :param episode: the run's episode number.
        """
        self.scene_seed = scene_seed(self.seed_base, episode) if self.varies else None
        return self.reset(seed=self.scene_seed)

    def _new_scene(self, inner_obs: np.ndarray) -> None:
        """Read the placement and (with ``adapt``) refit the KMP through the scene's via-points."""
        if self.task.scene is None:
            return
        scene = episode_scene(self.world, inner_obs, adapt=self.adapt, cache=self._scene_cache)
        self._scene_cache = scene
        self.placement, self.via_points = scene.placement, scene.via_points
        self.mapping.use_model(scene.model)
        mean = scene.model.grid_mean
        self.via_error = max((float(np.max(np.abs(mean[n] - p))) for n, p in scene.via_points), default=0.0)
        self.max_violation = -np.inf

    def scene_row(self) -> dict | None:
        """This episode's scene for ``scenes.csv`` (None for a task whose scene does not vary): the reset seed,
        whether the KMP was adapted, the via-points, the largest |adapted mean - via-point| at their steps, the
        largest violation of a hard constraint by a commanded P_t (``max(c - G P_t)``, <= 0 when every one held;
        rounding leaves up to ~1e-13 on a command on the constraint's edge), whether that is a violation
        (``violated``: more than ``VIOLATION_TOL``, as ``violation_steps`` counts) and the placement."""
        if not self.varies:
            return None
        return {"seed": self.scene_seed, "adapted": bool(self.via_points), "via_points": len(self.via_points),
                "via_error": self.via_error, "max_violation": self.max_violation,
                "violated": int(self.max_violation > VIOLATION_TOL), **self.placement}

    def _command(self, t: int, a: np.ndarray, L: np.ndarray, info: dict):
        """Eq. 5 (policy) or eq. 6 (correction): (P_t, xi, the action the transition stores)."""
        p_h = None
        if self._correction is not None:  # projected onto the workspace box (counted), whatever the control
            p_h = np.clip(self._correction, self.world.low, self.world.high)
            info["projected"] = bool(np.any(p_h != self._correction))
        if self.delta is not None:
            return self._delta_command(a, p_h, info)
        if p_h is not None:
            iv = self.mapping.intervene(t, p_h, L)
            info.update(intervened=True, clipped=iv.clipped, xi_h=iv.xi, raw_action=iv.raw_action)
            return p_h, iv.xi, iv.action
        desired, xi = self.mapping.act(t, a, L)
        info["workspace_exit"] = bool(np.any(desired < self.world.low - VIOLATION_TOL)
                                      or np.any(desired > self.world.high + VIOLATION_TOL))  # (the QP's rounding)
        return desired, xi, a

    def _delta_command(self, a: np.ndarray, p_h: np.ndarray | None, info: dict):
        """Delta control (:class:`~khgrl.common.tasks.delta.DeltaControl`): the policy's displacement, or the
        takeover action towards the (workspace-projected) P_h; xi is zero (there is no null space)."""
        zero = np.zeros(self.world.out_dim)
        if p_h is not None:
            a_h, clipped = self.delta.invert(self.position, p_h)
            info.update(intervened=True, clipped=clipped, xi_h=zero, raw_action=a_h)
            return self.delta.act(self.position, a_h)[0], zero, a_h
        desired, exited = self.delta.act(self.position, a)
        info["workspace_exit"] = exited
        return desired, zero, a

    def step(self, action):
        if self._done:
            raise RuntimeError("step() called after the episode ended: call reset()")
        t, o = self.t, self.world.out_dim
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (o,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be a finite ({o},) array, got {action!r}")
        a = np.clip(a, -1.0, 1.0)
        L = self.mapping.scale_at(t, self.position)
        mean = self.mapping.mean(t)
        info: dict = {"intervened": False, "clipped": False, "projected": False, "workspace_exit": False,
                      "rate_limited": False}
        desired, xi, stored = self._command(t, a, L, info)
        dp = desired - mean
        r_a = -self.task.action_cost * float(dp @ dp) if self.delta is None else 0.0
        if self.limiter is not None:  # what the robot is sent
            desired, info["rate_limited"] = self.limiter.limit(desired)
        violation = float(np.max(self.world.c - self.world.G @ desired, initial=-np.inf))  # (> 0: a row violated)
        info["violation"] = violation > VIOLATION_TOL
        env_action = desired if self.task.command is None else self.task.command(self.inner, desired)
        inner_obs, r_env, term, trunc, inner_info = self.inner.step(env_action)
        self._inner_obs = inner_obs
        self.sent(desired, inner_obs)
        if self.task.scene is not None:
            self.max_violation = max(self.max_violation, violation)
        self.trail.append(self.position.copy())
        self.t += 1
        terminated = bool(term)
        truncated = (not terminated) and (bool(trunc) or self.t >= self.horizon)
        self._done = terminated or truncated
        info = {**inner_info, **info}
        info.update(r_a=r_a, success=bool(inner_info.get(self.task.success_key, False)),
                    action=np.asarray(stored, dtype=np.float32), xi=xi, scale=L, desired=desired,
                    phase=float(self.mapping.phases[t]), t=t,
                    constraints_active=0 if info["intervened"] or self.delta
                    else self.mapping.model.step_info.active_rows)
        return self._obs(), r_a + float(r_env), terminated, truncated, info

    def sent(self, p: np.ndarray, inner_obs: np.ndarray) -> None:
        """``p`` was sent and the task's environment answered ``inner_obs``: the robot's position, the position last
        sent and its step (what the next step and the path back to the start go on from).

        :param p: the position sent, (O,).
        :param inner_obs: the task environment's observation after it.
        """
        self.position = self._locate(inner_obs, p)
        self.desired = p
        self.sent_step, self.anchor = p - self.anchor, p.copy()

    def reset_path(self, limits: tuple[float, float], max_steps: int = 10_000):
        """Between episodes: the path back to the start within ``limits`` (:func:`khgrl.common.tasks.motion.reset_path`:
        from the last step sent, at its velocity); yields each position sent.

        :param limits: ``(max_speed, max_accel)`` in units of the demonstrations' largest step.
        :param max_steps: a bound on the path's length.
        """
        return reset_path(self, limits, max_steps)

    def hold(self) -> None:
        """The actor holds the robot (the e-stop, a pause, a wait for ready or for the learner, a silent human, a
        stalled loop): give the task's ``hold`` adapter the position last sent, about once a control period (without
        one: nothing is sent; the robot's controller keeps its last target). The robot stands still: the rate limits
        restart at rest from where it is measured -- the observation the adapter returns -- or, when it returns none,
        from the position last sent, which a position-controlled arm reaches while held
        (:mod:`khgrl.common.tasks.motion`). Every kind of hold goes through here."""
        obs = None if self.task.hold is None else self.task.hold(self.inner, self.desired.copy())
        self.anchor = self.desired.copy()
        if obs is not None:
            self._inner_obs = measured(self, obs)
            self.position = self._locate(self._inner_obs, self.desired)
            self.anchor = np.clip(self.position, self.world.low, self.world.high)
        self.sent_step = np.zeros_like(self.anchor)
        for lim in (self.limiter, self.path_limiter):
            if lim is not None:
                lim.reset(self.anchor)

    # --------------------------------------------------------------- descriptor and drawing
    def descriptor(self, spec: str = ""):
        """This run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (what the actor announces;
        :func:`khgrl.common.tasks.env_descriptor.descriptor`)."""
        from khgrl.common.tasks.env_descriptor import descriptor

        return descriptor(self, spec)

    def render(self):
        """An RGB image of the task views (:class:`~khgrl.common.tasks.render.TaskRenderer`), or None without a mode."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode")
            return None
        from khgrl.common.tasks.render import TaskRenderer, frame_from_env

        if self._renderer is None:
            self._renderer = TaskRenderer(self.descriptor())
        return self._renderer.render_rgb(frame_from_env(self))

    def close(self) -> None:
        self.inner.close()

