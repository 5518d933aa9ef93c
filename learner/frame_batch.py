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
from khgrl.common.wire.frames import PREV, pack_frames

__all__ = ["PREV", "pack_frames", "split_space"]

# (the batch form is the wire's too: :mod:`khgrl.common.wire.frames`, where it lives)


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
