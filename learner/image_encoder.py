"""The learner's image encoder (issue 37, point 4): an SB3 features extractor for a ``Dict`` observation space of
named camera images (``H x W x C`` uint8) and state vectors, with DrQ's random-shift augmentation.

Architecture, per camera (the encoder of DrQ, Kostrikov, Yarats & Fergus 2020, and of SAC-AE, Yarats et al. 2019,
whose conv stack DrQ-v2, Yarats et al. 2021, keeps): a *trunk* of 4 conv layers of 32 channels, 3 x 3, the first of
stride 2 (DrQ's, for 84 x 84 images; larger images a larger first stride, :func:`first_stride`: 3 for 128 x 128, so
that the trunk's output stays about DrQ's size), each followed by ReLU; then a *head* Linear -> LayerNorm -> tanh to
``features_dim``. The features of all cameras and then the state vectors (the space's other keys, in its order) are
concatenated. Images are scaled to [0, 1] here (the policy must not scale them: ``normalize_images=False``,
:mod:`khgrl.learner.image_policy` sets it) and permuted to channel-first when the space is channel-last. (SB3 itself
wraps an environment whose Dict holds channel-last images in ``VecTransposeImage``; then the model's space, the
replay buffer's arrays and what reaches this module are channel-first already, and nothing is permuted.)

One trunk and head per camera, not one shared across cameras: the cameras see different things (a wrist camera
the gripper and the object close up, a front camera the scene), and may differ in size; a shared trunk would save
only the trunk's 28 k parameters per camera (the head's Linear, ``32 x 36 x 36 x 50`` = 2.1 M for a 128 x 128
image, cannot be shared between cameras of different sizes anyway), and the compute is the same, each image goes
through one trunk once. A weights file of one trunk still loads into every camera's
(:mod:`khgrl.learner.encoder_weights`).

Augmentation (DrQ): each image padded by 4 pixels (replicate) and cropped back to its size at a random offset,
independently per sample and camera, only while the module is in training mode (identity in eval mode, so an
actor's ``predict`` sees the image as is). The offsets come from the module's own ``torch.Generator``, seeded by
``seed`` or, without one, from torch's global generator when the module is built (so an SB3 model built with a
seed is reproducible).

``frozen``: the trunks' parameters get ``requires_grad = False``, the trunks stay in eval mode and run without
autograd; the heads still train. The augmentation is applied before the trunk, so it stays on with a frozen trunk
(it regularises the heads and the critics that learn on its features); ``augment=False`` turns it off.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space_channels_first
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn
from torch.nn import functional as F

__all__ = ["ImageEncoder", "RandomShift", "random_shift", "conv_trunk", "image_keys", "DEFAULT_FEATURES", "PAD"]

DEFAULT_FEATURES = 50  # per camera: DrQ's and DrQ-v2's feature_dim
PAD = 4  # DrQ's random-shift padding, pixels
DRQ_INPUT = 84  # the image side DrQ's stack was made for (stride 2 first)
CHANNELS = 32  # DrQ's conv width


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator) -> torch.Tensor:
    """Each image padded by ``pad`` pixels (edge pixels replicated) and cropped back to its size at an offset drawn
    uniformly from ``0 .. 2 pad`` in each axis, per sample (DrQ's random shift, in integer pixels).

    :param images: a float ``(B, C, H, W)`` batch
    :param pad: padding in pixels
    :param generator: the CPU generator the offsets are drawn from
    :return: the shifted batch, ``(B, C, H, W)``
    """
    b, _, h, w = images.shape
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
    offsets = torch.randint(0, 2 * pad + 1, (b, 2), generator=generator).to(images.device, non_blocking=True)
    rows = offsets[:, :1] + torch.arange(h, device=images.device)  # (B, H)
    cols = offsets[:, 1:] + torch.arange(w, device=images.device)  # (B, W)
    batch = torch.arange(b, device=images.device)[:, None, None]
    # advanced indices around a slice: the result is (B, H, W, C)
    return padded[batch, :, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)


class RandomShift(nn.Module):
    """DrQ's random shift (:func:`random_shift`) in training mode, the identity in eval mode.

    :param pad: padding in pixels (0: no augmentation)
    :param seed: the offsets' generator seed (None: drawn from torch's global generator)
    """

    def __init__(self, pad: int = PAD, seed: int | None = None) -> None:
        super().__init__()
        if pad < 0:
            raise ValueError(f"pad must be >= 0, not {pad}")
        self.pad = pad
        self.generator = torch.Generator()
        self.reseed(seed)

    def reseed(self, seed: int | None) -> None:
        """Seed the offsets' generator.

        :param seed: the seed (None: drawn from torch's global generator)
        """
        self.generator.manual_seed(int(torch.randint(2 ** 62, (1,))) if seed is None else int(seed))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """The shifted images in training mode, ``images`` itself in eval mode.

        :param images: a float ``(B, C, H, W)`` batch
        """
        if not self.training or self.pad == 0:
            return images
        return random_shift(images, self.pad, self.generator)


def first_stride(height: int, width: int) -> int:
    """The first conv layer's stride: 2, DrQ's, for its 84 x 84 images and smaller, and larger for larger images so
    that the trunk's output stays about DrQ's 35 x 35 (:data:`DRQ_INPUT` / 2 per first-layer pixel): 3 for 128 x 128
    (an output of 36 x 36 instead of 57 x 57: the head's Linear 2.6x smaller, the three later layers 2.5x cheaper).

    :param height: the image's height (pixels)
    :param width: its width
    """
    return max(2, round(max(height, width) / (DRQ_INPUT / 2)))


def conv_trunk(in_channels: int, stride: int = 2) -> nn.Sequential:
    """DrQ's conv stack: 4 conv layers of 32 channels, 3 x 3, the first of stride ``stride`` (DrQ's 2;
    :func:`first_stride`), ReLU after each, flattened. Its ``state_dict`` keys are ``{0,2,4,6}.{weight,bias}``
    (the stride is not a parameter: a weights file loads into a trunk of any stride).

    :param in_channels: the image's channels
    :param stride: the first layer's stride
    """
    layers: list[nn.Module] = []
    for i in range(4):
        layers += [nn.Conv2d(in_channels if i == 0 else CHANNELS, CHANNELS, 3, stride=stride if i == 0 else 1),
                   nn.ReLU()]
    return nn.Sequential(*layers, nn.Flatten())


def image_keys(observation_space: spaces.Dict) -> tuple[list[str], list[str]]:
    """The camera keys (3-D uint8 ``Box``) and the vector keys (1-D ``Box``) of a Dict space, in its order.

    :param observation_space: the Dict observation space
    :raises ValueError: not a Dict, a key that is neither, or no camera
    """
    if not isinstance(observation_space, spaces.Dict):
        raise ValueError(f"the image encoder needs a Dict observation space, not {type(observation_space).__name__}")
    cameras, vectors = [], []
    for key, space in observation_space.spaces.items():
        if isinstance(space, spaces.Box) and len(space.shape) == 3 and space.dtype == np.uint8:
            cameras.append(key)
        elif isinstance(space, spaces.Box) and len(space.shape) == 1:
            vectors.append(key)
        else:
            raise ValueError(f"observation key {key!r}: {space} is neither an H x W x C uint8 image nor a vector")
    if not cameras:
        raise ValueError("the observation space has no image (an H x W x C uint8 Box)")
    return cameras, vectors


class ImageEncoder(BaseFeaturesExtractor):
    """Per camera a DrQ trunk and head, the state vectors appended (the module docstring).

    :param observation_space: a Dict of camera images (``H x W x C`` or, after SB3's ``VecTransposeImage``,
        ``C x H x W`` uint8) and 1-D state vectors
    :param features_dim: each camera's feature size
    :param frozen: trunks not trained (``requires_grad`` False, kept in eval mode)
    :param augment: DrQ's random shift in training mode
    :param pad: its padding in pixels
    :param seed: its generator's seed (None: drawn from torch's global generator)
    """

    def __init__(self, observation_space: spaces.Dict, features_dim: int = DEFAULT_FEATURES, frozen: bool = False,
                 augment: bool = True, pad: int = PAD, seed: int | None = None) -> None:
        cameras, vectors = image_keys(observation_space)
        state_dim = sum(int(observation_space[k].shape[0]) for k in vectors)
        super().__init__(observation_space, features_dim * len(cameras) + state_dim)
        self.cameras, self.vectors = cameras, vectors
        self.channels_last = {k: not is_image_space_channels_first(observation_space[k]) for k in cameras}
        self.shift = RandomShift(pad if augment else 0, seed)
        self.trunks, self.heads = nn.ModuleDict(), nn.ModuleDict()
        for key in cameras:
            shape = observation_space[key].shape
            c, h, w = (shape[2], shape[0], shape[1]) if self.channels_last[key] else shape
            trunk = conv_trunk(c, first_stride(h, w))
            with torch.no_grad():
                flat = int(trunk(torch.zeros(1, c, h, w)).shape[1])
            self.trunks[key] = trunk
            self.heads[key] = nn.Sequential(nn.Linear(flat, features_dim), nn.LayerNorm(features_dim), nn.Tanh())
        self.frozen = False
        if frozen:
            self.freeze()

    def freeze(self) -> None:
        """Stop training the trunks: ``requires_grad`` False, eval mode from now on."""
        self.frozen = True
        self.trunks.requires_grad_(False)
        self.trunks.eval()

    def train(self, mode: bool = True) -> ImageEncoder:
        """nn.Module's ``train``, the trunks kept in eval mode when frozen.

        :param mode: training mode
        """
        super().train(mode)
        if self.frozen:
            self.trunks.eval()
        return self

    def encode(self, key: str, image: torch.Tensor) -> torch.Tensor:
        """One camera's features.

        :param key: the camera
        :param image: its batch as the space lays it out, uint8 or float in 0 .. 255
        """
        x = image.float()
        if self.channels_last[key]:
            x = x.permute(0, 3, 1, 2)
        x = self.shift(x / 255.0)
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.frozen):
            flat = self.trunks[key](x)
        return self.heads[key](flat)

    def forward(self, observations: dict[str, Any]) -> torch.Tensor:
        """The cameras' features, then the state vectors: ``(B, features_dim)``.

        :param observations: tensors by key (SB3's preprocessed observation: floats, not scaled)
        """
        parts = [self.encode(key, observations[key]) for key in self.cameras]
        parts += [observations[key].float().reshape(len(observations[key]), -1) for key in self.vectors]
        return torch.cat(parts, dim=1)
