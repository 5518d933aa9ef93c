"""What ``khgrl up`` checks before it starts any process or writes anything: the run's task, built once (its
demonstrations, constraints, first scene's via-points, scripted human), and the human-input device the run names.
A mistake is one line and exit 2 (README, "Bring your own task")."""

from __future__ import annotations

from khgrl.common.config.settings import HUMAN_METHODS, RunConfig
from khgrl.human_bridge.hid_devices import check_human_device

__all__ = ["check_task"]


def check_task(cfg: RunConfig, bounds: dict | None = None):
    """Build the run's task once before any process starts, so a bad task definition (or a missing human-input
    device) is one clear error here; returns its descriptor.

    :param cfg: the run's settings
    :param bounds: filled (if given) with the task's value bounds and how they came about: stated by the task, or
        derived with the rule and margin of :mod:`khgrl.common.tasks.derived_bounds` (``config.json``'s
        ``runtime.task_bounds``)
    :raises TaskError: naming what is wrong with the task
    :raises ValueError: ``--human spacemouse`` without a SpaceMouse plugged in
    """
    from khgrl.common.tasks.api import TaskError, load_task
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    check_human_device(cfg.human)  # (first: it takes no time)
    task = load_task(cfg.task_spec, cfg.demos or None)
    env = KGRLEnv(task, seed=cfg.seed)
    try:
        if env.varies:  # the first scene's via-points, checked here rather than in an actor after launch
            env.reset_episode(1)
    finally:
        env.close()
    if cfg.method in HUMAN_METHODS and cfg.human == "scripted" and task.scripted_human is None:
        raise TaskError(f"task {task.name!r} has no scripted_human: choose --human gui or --human none")
    descriptor = env.descriptor(cfg.task_spec)
    if bounds is not None:
        from khgrl.common.tasks.env_descriptor import task_bounds

        bounds.update(task_bounds(env)[1], learner_reward_bound=descriptor.reward_bound)
    return descriptor
