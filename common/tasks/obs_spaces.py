"""Camera observations: the shapes of a task whose environment observes named images plus a state vector (issue 37).

A task declares cameras with ``Task(state_key=..., image_keys=(...))`` (:class:`~khgrl.common.tasks.api.Task`).
Its environment's observation space is then a flat ``spaces.Dict`` holding

* ``state_key``: the state vector, a 1-D float Box of at most :data:`~khgrl.common.tasks.api.MAX_DIM` entries
  (e.g. gym-hil's ``agent_pos``); the task's ``position(obs)`` reads the robot from it;
* each of ``image_keys``: an image, a Box of dtype uint8 and shape (H, W, C) with 1 <= H, W <= :data:`MAX_SIDE`
  and C in :data:`CHANNELS` (grey, RGB, RGBA); at most :data:`MAX_CAMERAS` of them;
* optionally other keys the policy does not observe: what only the task's own functions read (``position``,
  ``Scene.describe`` / ``via_points``, ``scripted_human`` get the environment's whole observation), e.g. a
  simulator's true object position that a scripted teacher uses.

The policy's observation (:func:`policy_space`, :func:`policy_obs`) is then a ``spaces.Dict``: ``"state"`` = the
state vector, the phase s and the deviation from the KMP mean (float32, what a vector task observes, with the state
vector in place of the environment's observation), plus every image unchanged (uint8, under its own key). A task
without cameras (``image_keys`` empty) keeps its 1-D Box observation: :func:`camera_layout` gives None and nothing
here applies.

The limits (the wire's: the task descriptor's ``cameras`` carries what is checked here) keep one transition
small enough to ship and store (4 RGBA cameras of 256 x 256 are 1 MiB); every
mistake is one :class:`~khgrl.common.tasks.api.TaskError` naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from khgrl.common.tasks.api import MAX_DIM, Task, TaskError
from khgrl.common.wire.descriptor import CAMERA_NAME, CHANNELS, MAX_CAMERAS, MAX_SIDE, STATE

__all__ = ["MAX_CAMERAS", "MAX_SIDE", "CHANNELS", "STATE", "CameraLayout", "camera_layout", "policy_space",
           "policy_obs", "state_of"]


@dataclass(frozen=True)
class CameraLayout:
    """The checked shape of a camera task's observation.

    :param state_key: the environment's key of the state vector.
    :param state: its Box (1-D).
    :param images: image key -> its Box (H, W, C) uint8, in the task's order.
    """

    state_key: str
    state: spaces.Box
    images: dict[str, spaces.Box]


def _declared(task: Task) -> tuple[str, tuple[str, ...]] | None:
    """(state key, image keys) the task declares, checked without its environment (None: a vector task)."""
    keys, state_key = tuple(task.image_keys), task.state_key
    if not keys and state_key is None:
        return None
    if not keys or not isinstance(state_key, str) or not state_key:
        raise TaskError(f"task {task.name!r}: a camera task names both its state key and at least one image key, "
                        f"got state_key={state_key!r}, image_keys={keys!r}")
    if len(keys) > MAX_CAMERAS:
        raise TaskError(f"task {task.name!r}: {len(keys)} image keys {keys!r}, at most {MAX_CAMERAS} cameras")
    for k in keys:
        if not isinstance(k, str) or not CAMERA_NAME.match(k) or k == STATE or k == state_key or keys.count(k) > 1:
            raise TaskError(f"task {task.name!r}: image key {k!r} must be a unique short identifier (letters, "
                            f"digits, _ . -) other than {STATE!r} and the state key {state_key!r}")
    return state_key, keys


def _check_image(task: Task, key: str, box: Any) -> spaces.Box:
    """The image space of ``key``, checked (see the module docstring)."""
    if not isinstance(box, spaces.Box):
        raise TaskError(f"task {task.name!r}: image key {key!r} must be a Box, got {box}")
    if box.dtype != np.uint8:
        raise TaskError(f"task {task.name!r}: image key {key!r} must have dtype uint8, got {box.dtype}")
    shape = box.shape
    if len(shape) != 3:
        raise TaskError(f"task {task.name!r}: image key {key!r} must be 3-D (H, W, C), got shape {shape}")
    h, w, c = shape
    if not (1 <= h <= MAX_SIDE and 1 <= w <= MAX_SIDE) or c not in CHANNELS:
        raise TaskError(f"task {task.name!r}: image key {key!r} has shape {shape}; at most {MAX_SIDE} x {MAX_SIDE} "
                        f"pixels and C in {CHANNELS}")
    return box


def _check_state(task: Task, key: str, box: Any) -> spaces.Box:
    """The state space of ``key``, checked: a 1-D float Box of 1..MAX_DIM entries."""
    if not isinstance(box, spaces.Box) or len(box.shape) != 1 or not np.issubdtype(box.dtype, np.floating):
        raise TaskError(f"task {task.name!r}: state key {key!r} must be a 1-D float Box, got {box}")
    if not 1 <= box.shape[0] <= MAX_DIM:
        raise TaskError(f"task {task.name!r}: state key {key!r} has {box.shape[0]} entries, 1 to {MAX_DIM} allowed")
    return box


def camera_layout(task: Task, space: Any) -> CameraLayout | None:
    """The layout of a camera task's observation space, checked against its declaration; None for a vector task.

    :param task: the task (its ``state_key`` and ``image_keys``).
    :param space: its environment's observation space.
    :raises TaskError: naming the key that is missing or wrong.
    """
    declared = _declared(task)
    if declared is None:
        return None
    state_key, keys = declared
    if not isinstance(space, spaces.Dict):
        raise TaskError(f"task {task.name!r} declares cameras {keys!r}: its environment's observation space must be "
                        f"a spaces.Dict, got {space}")
    for k in (state_key, *keys):
        if k not in space.spaces:
            raise TaskError(f"task {task.name!r}: key {k!r} is not in the environment's observation space (keys "
                            f"{list(space.spaces)})")
    return CameraLayout(state_key=state_key, state=_check_state(task, state_key, space[state_key]),
                        images={k: _check_image(task, k, space[k]) for k in keys})


def policy_space(layout: CameraLayout, out_dim: int) -> spaces.Dict:
    """The policy's observation space of a camera task: ``"state"`` (state, phase, deviation; float32) and the
    images unchanged.

    :param layout: the task's :class:`CameraLayout`.
    :param out_dim: O, the command's dimension (the deviation's).
    """
    st = layout.state
    state = spaces.Box(low=np.concatenate([st.low.astype(np.float64), [0.0], -np.ones(out_dim)]).astype(np.float32),
                       high=np.concatenate([st.high.astype(np.float64), [1.0], np.ones(out_dim)]).astype(np.float32),
                       dtype=np.float32)
    return spaces.Dict({STATE: state, **layout.images})


def policy_obs(layout: CameraLayout, inner_obs: Any, phase: float, deviation: np.ndarray) -> dict[str, np.ndarray]:
    """The policy's observation of a camera task from its environment's observation.

    :param layout: the task's :class:`CameraLayout`.
    :param inner_obs: the environment's observation (a mapping of its keys).
    :param phase: s at this step.
    :param deviation: the robot's deviation from the KMP mean, clipped (O,).
    """
    state = np.asarray(inner_obs[layout.state_key], dtype=np.float64).reshape(-1)
    out = {STATE: np.concatenate([state, [phase], deviation]).astype(np.float32)}
    for k, box in layout.images.items():
        img = np.asarray(inner_obs[k])
        if img.shape != box.shape or img.dtype != np.uint8:
            raise TaskError(f"image key {k!r}: the environment gave {img.dtype} {img.shape}, its space says uint8 "
                            f"{box.shape}")
        out[k] = img
    return out


def state_of(task: Task, obs: Any) -> Any:
    """The state vector of a camera task's observation (``obs[task.state_key]``); a vector task's ``obs`` as it is.

    :param task: the task.
    :param obs: its environment's observation.
    """
    return obs[task.state_key] if task.image_keys and isinstance(obs, dict) else obs
