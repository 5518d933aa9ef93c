"""The task API: what a user supplies to run KhGRL on their own robot or simulator (README, "Bring your own task").

A :class:`Task` holds

* ``make_env`` -- a factory of a Gymnasium environment whose action is the *desired position* P_t in R^O
  (the command the KGRL mapping produces, eq. 5), or any environment plus ``command``, an adapter from P_t to
  that environment's own action (e.g. a delta end-effector action);
* ``demos`` -- demonstrations (M, N, O) as an array or a .npz/.csv file (:mod:`khgrl.common.tasks.demos`), the KMP
settings
  (:class:`~khgrl.common.kmp.fit.KMPConfig`), the workspace box (always a hard constraint) and optional further hard
  linear constraints ``G P >= c`` (math.md §3);
* the default exploration scale L0 and whether KhGRL learns it from the human (paper Section III-C);
* the value bounds the learner holds the task's transitions to: ``reward_bound`` (the largest |reward| of the
  environment) and ``obs_bound`` (the largest |observation| in any dimension; within it the observation space's own
  bounds apply): a batch beyond them is refused (:func:`value_bounds`). A bound the task does not state (None, the
  default) is derived from its demonstrations and two random episodes with a margin of 4
  (:mod:`khgrl.common.tasks.derived_bounds`);
* optionally: ``scene``, a scene that changes every episode and the via-points that adapt the KMP to it
  (:class:`~khgrl.common.tasks.scene.Scene`);
* optionally: cameras, ``state_key`` and ``image_keys``: the environment observes named images plus a state vector
  (a ``spaces.Dict``; :mod:`khgrl.common.tasks.obs_spaces`);
* optionally: ``position`` (where the robot is, in command coordinates, from the environment's observation;
  default: the command last sent), ``scripted_human`` (P_h or None for the step whose KMP mean is given; it may
  also ask for the step, the phase, the robot's position and the observation: :func:`call_scripted_human`),
  and drawing hints (:class:`View`).

The policy observes the environment's observation, the phase s and the robot's deviation from the KMP mean
(clipped to [-1, 1]); the reward is the environment's plus the action cost r_a = -``action_cost`` |P_t - eta0_t|^2
(eq. 7). :func:`load_task` turns a spec (``passage:high_cov`` or ``my_package.my_module:make_task``) into a
checked task; every mistake in a task definition is one :class:`TaskError` naming what is wrong.

One module of ~325 lines on purpose: the task author's whole API in one file: the Task, its shapes, loading a task
by name.
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from khgrl.common.kmp.fit import KMPConfig
from khgrl.common.lerobot.demos import is_lerobot_spec
from khgrl.common.tasks.scene import Scene, ViaPoint, scene_seed

__all__ = ["Task", "View", "Scene", "ViaPoint", "scene_seed", "Cuboid", "Sphere", "Point", "TaskError", "load_task",
           "BUILTIN_TASKS", "MAX_DIM", "HUMAN_INPUTS", "scripted_human_inputs", "call_scripted_human",
           "MAX_DECLARED_BOUND", "task_demos"]

MAX_DIM = 64  # command (O) and observation sizes a task may have (also the wire's bound)
MAX_DECLARED_BOUND = 1e9  # the largest reward_bound / obs_bound a task may declare (float32 training stays finite)


class TaskError(ValueError):
    """A task definition that cannot run; the text names the task and what is wrong."""


@dataclass(frozen=True)
class Cuboid:
    """An axis-aligned box in command coordinates (a keep-out zone, a table, a target region)."""

    name: str
    low: tuple[float, ...]
    high: tuple[float, ...]
    kind: str = "box"


@dataclass(frozen=True)
class Sphere:
    """A ball (a circle in a 2-D view) in command coordinates."""

    name: str
    center: tuple[float, ...]
    radius: float
    kind: str = "sphere"


@dataclass(frozen=True)
class Point:
    """A marked point (start, goal) in command coordinates."""

    name: str
    at: tuple[float, ...]
    kind: str = "point"


Shape = Cuboid | Sphere | Point


@dataclass(frozen=True)
class View:
    """Drawing hints for the GUI, monitors and ``khgrl eval --gif``.

    :param axes: the two command axes of the main 2-D view (horizontal, vertical).
    :param third: a third axis shown in a second view against the first (None: no second view).
    :param names: a name per command axis (default x, y, z, y3, ...).
    :param shapes: named objects drawn in the views.
    """

    axes: tuple[int, int] = (0, 1)
    third: int | None = None
    names: tuple[str, ...] = ()
    shapes: tuple[Shape, ...] = ()


@dataclass(frozen=True)
class Task:
    """One task: the environment, the demonstrations and the KGRL settings. See the module docstring.

    :param name: a short name (shown in logs, frames and plots).
    :param make_env: ``make_env(seed) -> gymnasium.Env`` (called once per actor, with the actor's seed).
    :param demos: (M, N, O) demonstrations or a path to a .npz/.csv file; None for a task that is always run
        with ``--demos FILE`` (which replaces this field).
    :param workspace: (low, high) of the box P_t must stay in (a hard constraint; corrections are projected
        onto it).
    :param kmp: GMM/GMR and LC-NS-KMP settings.
    :param constraints: optional further hard constraints (G (K, O), c (K,)) with G P >= c.
    :param default_scale: L0 (a number or one per output).
    :param learn_scale: KhGRL refits L from the human's corrections.
    :param action_cost: weight of r_a = -action_cost |P_t - eta0_t|^2 (eq. 7).
    :param command: adapter ``command(env, p_t) -> env action`` (None: the action is P_t itself).
    :param position: ``position(obs) -> (O,)`` the robot in command coordinates (None: the command last sent).
    :param push: ``push(env, p_h)``, simulation only (``--physical scripted``): the scripted physical human pushes the
        robot towards ``p_h`` with a force during the next step (None: lets go); a robot whose controller yields to
        force (None: the task cannot be pushed).
    :param contact: ``contact(env) -> bool``: the robot touches what it means to now (an object in its closed gripper,
        a surface it presses): ``--physical`` starts no interaction then (to positions, a hand and a held object
        look the same). None: never.
    :param hold: ``hold(env, p_t)``, called about once a period while the actor holds the robot, with the position
        last sent (None: nothing is sent; a position-controlled arm keeps its last target); it may return the
        observation read while held: the rate limits restart there (else from p_t; :mod:`khgrl.common.tasks.motion`).
    :param scripted_human: ``scripted_human(mean) -> P_h or None`` for the step whose KMP mean is ``mean``; a
        function that names any of ``step``, ``phase``, ``position``, ``obs`` as parameters (or takes
        ``**kwargs``) gets those too (:func:`call_scripted_human`).
    :param view: drawing hints.
    :param success_key: the ``info`` key that marks a successful episode end.
    :param reward_bound: the largest |reward| the environment gives; the learner refuses a batch with a reward
        beyond it plus the largest action cost (:func:`value_bounds`). None (default): derived
        (:mod:`khgrl.common.tasks.derived_bounds`: 4 x the largest |reward| seen replaying the demonstrations and
        two random episodes, rounded up to a power of two).
    :param obs_bound: the largest |observation| in any dimension, whatever the observation space says; within it
        the space's own bounds apply (with a margin of a tenth of their width). None (default): derived as
        ``reward_bound`` is.
    :param scene: how the scene varies per episode and adapts the KMP (None: one fixed scene;
        :mod:`khgrl.common.tasks.scene`).
    :param state_key: a task with cameras: the key of the state vector in its environment's ``spaces.Dict``
        observation (``position`` reads the robot from it); None: a 1-D Box observation
        (:mod:`khgrl.common.tasks.obs_spaces`).
    :param image_keys: a task with cameras: the keys of its images (uint8 (H, W, C)); the policy observes them
        unchanged beside the state vector, phase and deviation.
    """

    name: str
    make_env: Callable[[int], Any]
    demos: Any
    workspace: tuple[Sequence[float], Sequence[float]]
    kmp: KMPConfig = KMPConfig()
    constraints: tuple[Any, Any] | None = None
    default_scale: float | Sequence[float] = 10.0
    learn_scale: bool = True
    action_cost: float = 10.0
    command: Callable[[Any, np.ndarray], Any] | None = None
    position: Callable[[np.ndarray], np.ndarray] | None = None
    hold: Callable[[Any, np.ndarray], Any] | None = None
    push: Callable[[Any, np.ndarray | None], None] | None = None
    contact: Callable[[Any], bool] | None = None
    scripted_human: Callable[..., np.ndarray | None] | None = None
    view: View = field(default_factory=View)
    success_key: str = "success"
    reward_bound: float | None = None
    obs_bound: float | None = None
    scene: Scene | None = None
    state_key: str | None = None
    image_keys: tuple[str, ...] = ()

    def with_demos(self, demos: Any) -> "Task":
        """This task with other demonstrations (``--demos FILE``)."""
        return replace(self, demos=demos)


# ------------------------------------------------------------------------------------ the scripted human
HUMAN_INPUTS = ("step", "phase", "position", "obs")  # what a scripted human may ask for besides the KMP mean


def scripted_human_inputs(fn: Callable) -> tuple[str, ...]:
    """Which of :data:`HUMAN_INPUTS` ``fn`` takes, from its signature: those it names as parameters, all of them if
    it takes ``**kwargs``, none for the original one-argument ``scripted_human(mean)``.

    :param fn: a task's ``scripted_human``.
    """
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):  # a builtin or extension callable without a signature: the old call
        return ()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return HUMAN_INPUTS
    return tuple(n for n in HUMAN_INPUTS if n in params and params[n].kind is not inspect.Parameter.POSITIONAL_ONLY)


def call_scripted_human(fn: Callable, mean: np.ndarray, *, step: int, phase: float | None,
                        position: np.ndarray | None, obs: np.ndarray | None,
                        names: tuple[str, ...] | None = None) -> Any:
    """P_h (or None) from a task's ``scripted_human`` for one step: ``fn(mean)``, plus as keywords what it asks for
    (:func:`scripted_human_inputs`).

    :param fn: the task's ``scripted_human``.
    :param mean: the KMP mean eta0_t of the step (O,).
    :param step: the step t the correction is for (0-based).
    :param phase: its phase s_t = t / (N - 1).
    :param position: where the robot is before the step, in command coordinates (O,).
    :param obs: the environment's latest observation (None where there is none: the check when a task is built,
        and step 0 of an episode in a distributed run, whose word is given before the episode starts).
    :param names: ``scripted_human_inputs(fn)`` when the caller keeps it (None: read from the signature now).
    """
    names = scripted_human_inputs(fn) if names is None else names
    if not names:
        return fn(mean)
    given = {"step": step, "phase": phase, "position": position, "obs": obs}
    return fn(mean, **{n: given[n] for n in names})


# ------------------------------------------------------------------------------------ loading
BUILTIN_TASKS = {"passage": "khgrl.common.tasks.passage.task:make_task",
                 "fetch": "khgrl.common.tasks.fetch.task:make_task",
                 "panda": "khgrl.common.tasks.panda.task:make_task"}


def _import_factory(spec: str) -> tuple[Callable, list[str]]:
    """``module:callable`` (or ``builtin:arg``) -> the callable and its positional string arguments."""
    head, sep, tail = spec.partition(":")
    if head in BUILTIN_TASKS:
        module, _, attr = BUILTIN_TASKS[head].partition(":")
        args = [tail] if tail else []
    elif sep and tail:
        module, attr, args = head, tail, []
    else:
        raise TaskError(f"task {spec!r}: expected 'passage:SCENARIO' or 'package.module:callable'")
    try:
        mod = _import(module)
    except Exception as exc:  # noqa: BLE001 - a user module can fail to import in any way
        hint = (" (run khgrl from the directory that holds it, or put that directory on PYTHONPATH)"
                if isinstance(exc, ModuleNotFoundError) else "")
        raise TaskError(f"task {spec!r}: cannot import {module!r}: {type(exc).__name__}: {exc}{hint}") from None
    fn = getattr(mod, attr, None)
    if not callable(fn):
        raise TaskError(f"task {spec!r}: {module!r} has no callable {attr!r}")
    return fn, args


def _import(module: str):
    """Import ``module``; a module in the current directory is found without PYTHONPATH (as ``python -m``)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module.split(".")[0] or os.getcwd() in sys.path:
            raise
        sys.path.append(os.getcwd())
        return importlib.import_module(module)


def load_task(spec: str, demos: str | Path | None = None) -> Task:
    """The checked task of ``spec``, with ``demos`` (a file) in place of its own demonstrations if given.

    :param spec: ``passage:high_cov``, ``passage:low_cov`` or ``package.module:callable`` (a callable returning
        a :class:`Task`, or a :class:`Task` itself).
    :param demos: a .npz/.csv demonstration file that replaces the task's, or a LeRobot dataset
        ``lerobot:PATH[?feature=NAME&dims=A:B&n=N]`` (:mod:`khgrl.common.lerobot.demos`).
    :raises TaskError: naming what is wrong.
    """
    fn, args = _import_factory(spec)
    if isinstance(fn, Task):
        task = fn
    else:
        try:
            task = fn(*args)
        except TaskError:
            raise
        except Exception as exc:  # noqa: BLE001 - the user's factory
            raise TaskError(f"task {spec!r}: the factory raised {type(exc).__name__}: {exc}") from None
    if not isinstance(task, Task):
        raise TaskError(f"task {spec!r}: the factory returned {type(task).__name__}, not a khgrl.task.Task")
    if demos:
        task = task.with_demos(_lerobot_demos(task, str(demos)) if is_lerobot_spec(demos) else Path(demos))
    return task


def _lerobot_demos(task: Task, spec: str) -> np.ndarray:
    """``--demos lerobot:PATH...``: the dataset's episodes resampled to the task's N, checked against its O."""
    from khgrl.common.lerobot.demos import LeRobotDemoError, load_lerobot_demos  # the library: only here

    n = o = None
    if task.demos is not None:  # the task's own demonstrations give N and O
        _, n, o = task_demos(task).shape
    elif np.ndim(task.workspace[0]) == 1:
        o = len(task.workspace[0])
    try:
        return load_lerobot_demos(spec, n=n, o=o)
    except LeRobotDemoError as exc:
        raise TaskError(f"task {task.name!r}: {exc}") from None


def task_demos(task: Task) -> np.ndarray:
    """The task's demonstrations as checked float64 (M, N, O)."""
    from khgrl.common.tasks.demos import DemoFormatError, load_demos, validate_demos

    if task.demos is None:
        raise TaskError(f"task {task.name!r} has no demonstrations: Task.demos is None, so give --demos FILE")
    try:
        if isinstance(task.demos, (str, Path)):
            demos = load_demos(task.demos)
        else:
            demos = validate_demos(task.demos, "demos")
    except DemoFormatError as exc:
        raise TaskError(f"task {task.name!r}: {exc}") from None
    m, n, o = demos.shape
    if m < 2 or n < 10 or o > MAX_DIM:
        raise TaskError(f"task {task.name!r}: need M >= 2 demonstrations of N >= 10 steps and O <= {MAX_DIM} "
                        f"outputs, got (M, N, O) = {demos.shape}")
    return demos
