"""Image observations for the replay: their layout (:func:`split_space`: cameras and a state vector) and the batch
form of image transitions: each frame of a batch once, and per row two indices into them.

A batch of one actor's consecutive transitions carries its distinct frames (``frames[camera]``, shape
(m, H, W, C)) and per row ``obs_frame`` and ``next_frame``, indices into those frames. A row that does not start an
episode has ``obs_frame[r] == next_frame[r - 1]`` (the next observation of step t is the observation of step
t + 1). Row 0's observation is usually the previous batch's last next observation, which the learner already holds:
``obs_frame[0] == PREV`` says so and the frame is not sent again
(:meth:`~khgrl.learner.frame_replay.FrameReplayBuffer.add_frames` checks that it holds that frame at the batch's
``first_step``). :func:`pack_frames` makes this form from per-row observations; the frames come in the order a
stream produces them: a new episode's first observation, then each row's next observation. So an actor sends each
frame once: one per step, plus one per episode start.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

__all__ = ["PREV", "pack_frames", "split_space"]

PREV = -1  # ``obs_frame[0]``: the actor stream's last stored next-observation frame (the learner's pin)


def pack_frames(obs: dict[str, np.ndarray], next_obs: dict[str, np.ndarray], done: np.ndarray,
                cameras: list[str], continues: bool) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The batch form of per-row observations: the distinct frames and each row's ``obs_frame``/``next_frame``.

    :param obs: camera -> observations of the rows, shape (n, H, W, C)
    :param next_obs: camera -> next observations, shape (n, H, W, C)
    :param done: per row: terminated or truncated (the next row starts an episode)
    :param cameras: the camera keys to pack
    :param continues: row 0's observation is the previous batch's last next observation (:data:`PREV`)
    """
    n = len(done)
    new_obs = np.ones(n, dtype=bool)  # rows whose observation is a frame of its own: an episode's first
    new_obs[1:] = np.asarray(done[:-1], dtype=bool)
    if n:
        new_obs[0] = not continues
    next_frame = np.cumsum(new_obs.astype(np.int64) + 1) - 1
    obs_frame = np.empty(n, dtype=np.int64)
    obs_frame[new_obs] = next_frame[new_obs] - 1
    cont = np.flatnonzero(~new_obs)
    obs_frame[cont] = np.where(cont > 0, next_frame[np.maximum(cont - 1, 0)], PREV)
    m = int(next_frame[-1]) + 1 if n else 0
    frames = {}
    for k in cameras:
        out = np.empty((m, *next_obs[k].shape[1:]), dtype=next_obs[k].dtype)
        out[next_frame] = next_obs[k]
        out[obs_frame[new_obs]] = obs[k][new_obs]
        frames[k] = out
    return frames, obs_frame, next_frame


def split_space(space: spaces.Dict, state_key: str = "state") -> tuple[list[str], spaces.Box]:
    """The camera keys (uint8 boxes of shape (H, W, C)) and the state space of an observation space.

    :param space: the Dict observation space
    :param state_key: the key of the float32 state vector
    :raises ValueError: not a Dict, no state vector, or a key that is neither
    """
    if not isinstance(space, spaces.Dict):
        raise ValueError(f"FrameReplayBuffer needs a Dict observation space, not {type(space).__name__}")
    state = space.spaces.get(state_key)
    if not (isinstance(state, spaces.Box) and len(state.shape) == 1 and state.dtype == np.float32):
        raise ValueError(f"FrameReplayBuffer needs a float32 state vector under {state_key!r}, got {state}")
    cameras = [k for k in space.spaces if k != state_key]
    for k in cameras:
        s = space.spaces[k]
        if not (isinstance(s, spaces.Box) and s.dtype == np.uint8 and len(s.shape) == 3):
            raise ValueError(f"FrameReplayBuffer: {k!r} is neither the state nor a uint8 H x W x C camera: {s}")
    if not cameras:
        raise ValueError("FrameReplayBuffer needs at least one camera in the observation space")
    return cameras, state
