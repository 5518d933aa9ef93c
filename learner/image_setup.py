"""What an SB3 learner algorithm does differently for a camera task (issue 37, point 4): its policy, its replay
buffer and the frames it stores.

* The policy: for a ``spaces.Dict`` observation space (the task descriptor's ``cameras``,
  :func:`~khgrl.common.tasks.spaces.observation_space`) the algorithm's DrQ image policy
  (:mod:`khgrl.learner.image_policy`: one image encoder shared by actor and critics, trained by the critic loss),
  on the learner and on the actors alike, with :data:`FEATURES` features per camera. The actors get the policy's
  ``actor`` network -- the encoder included: its bytes grow with the image (DrQ's conv stack keeps the image's size
  but for its first stride, so the head's Linear has about ``32 x (H/s - 3) x (W/s - 3) x 50`` weights, ``s`` the
  first stride, 2 up to 84 x 84 and more above, :func:`~khgrl.learner.image_encoder.first_stride`): one 16 x 16
  camera gives a 154 kB actor with 64 x 64 hidden layers (122 kB of it the encoder), two 128 x 128 cameras (stride
  3) a 17.2 MB one with 256 x 256 (42 MB with DrQ's stride 2; the weights message allows 64 MiB).
* The replay buffer: :class:`~khgrl.learner.frame_replay.FrameReplayBuffer` (each frame once) through SB3's
  ``replay_buffer_class`` hook.
* SB3 holds channel-last images channel-first (its ``VecTransposeImage`` wraps the learner's spaces-only env), so
  the model's space and the buffer's frames are (C, H, W): :func:`buffer_frames` transposes a batch's frames.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

import numpy as np
from gymnasium import spaces

__all__ = ["FEATURES", "IMAGE_POLICIES", "is_camera_space", "image_policy", "buffer_frames", "describe_space"]

FEATURES = 50  # features per camera (DrQ's)
# --algo -> the image_policy helper of khgrl.learner.image_policy
IMAGE_POLICIES = {"tqc": "tqc_image_policy", "sac": "sac_image_policy", "sac_ln": "sac_ln_image_policy",
                  "sac_cta": "sac_ln_image_policy"}


def is_camera_space(space: Any) -> bool:
    """Whether ``space`` is a camera task's observation space (a Dict).

    :param space: an observation space
    """
    return isinstance(space, spaces.Dict)


def image_policy(algo: str, space: spaces.Dict) -> tuple[type, dict[str, Any]]:
    """The DrQ policy class of ``--algo`` and the ``policy_kwargs`` its image encoder needs (merge with
    ``net_arch``).

    :param algo: the algorithm's registered name
    :param space: the camera task's Dict observation space
    :raises ValueError: the algorithm has no image policy
    """
    if algo not in IMAGE_POLICIES:
        raise ValueError(f"--algo {algo} has no image policy (camera tasks: {', '.join(IMAGE_POLICIES)})")
    # (imported by name, as the algorithm registry imports its classes: the image policies import the algorithms'
    # policy classes, whose modules import the SB3 adapter that calls this)
    helper = getattr(import_module("khgrl.learner.image_policy"), IMAGE_POLICIES[algo])
    return helper(space, features_dim=FEATURES)


def buffer_frames(buffer: Any, frames: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A batch's frames (camera -> (m, H, W, C)) laid out as ``buffer`` stores them (channel-first where SB3 made
    its space so).

    :param buffer: the :class:`~khgrl.learner.frame_replay.FrameReplayBuffer`
    :param frames: the batch's frames
    """
    shapes = buffer.store.shapes
    return {k: v if tuple(v.shape[1:]) == shapes[k] else np.ascontiguousarray(v.transpose(0, 3, 1, 2))
            for k, v in frames.items()}


def describe_space(space: Any) -> str:
    """An observation space in a few words (an error message's).

    :param space: a Box or a camera task's Dict
    """
    if is_camera_space(space):
        return ", ".join(f"{k} {tuple(s.shape)}" for k, s in space.spaces.items())
    return str(space.shape[0])
