"""A user's pretrained encoder weights (``--encoder-weights FILE``, issue 37) loaded into the trunks of the
learner's image encoders (:class:`~khgrl.learner.image_encoder.ImageEncoder`), optionally frozen.

The file is a ``state_dict`` of tensors, read without unpickling code: ``torch.load(weights_only=True)``, or a
``.safetensors`` file when the ``safetensors`` package is installed. Two layouts:

* one trunk (DrQ's conv stack, keys ``0.weight``, ``0.bias``, ``2.weight`` ... ``6.bias``,
  :func:`~khgrl.learner.image_encoder.conv_trunk`): loaded into every camera's trunk;
* per camera (``front.0.weight`` ...: a camera's key, a dot, a trunk key): each camera's from its own keys, and
  every camera must have them.

Anything that does not fit is refused before anything is loaded, with the missing keys, the unexpected keys and
each shape mismatch named. The heads (Linear -> LayerNorm -> tanh) are not in the file: they are trained.
Loaded into every ImageEncoder of a policy: the one actor and critics share, and the target critic's copy.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from khgrl.learner.image_encoder import ImageEncoder
from torch import nn

__all__ = ["read_weights", "trunk_states", "load_encoder_weights", "EncoderWeightsError"]


class EncoderWeightsError(ValueError):
    """An encoder weights file that cannot be read or does not fit the encoder."""


def read_weights(path: str | Path) -> dict[str, torch.Tensor]:
    """A ``state_dict`` from a file: ``torch.load(weights_only=True)``, or safetensors for ``*.safetensors``.

    :param path: the file
    :raises EncoderWeightsError: unreadable, or not a mapping of names to tensors
    """
    path = Path(path)
    try:
        if path.suffix == ".safetensors":
            try:
                from safetensors.torch import load_file
            except ImportError:
                raise EncoderWeightsError(f"{path}: reading .safetensors needs the safetensors package (not "
                                          "installed); or save the state_dict with torch.save") from None
            state: Any = load_file(str(path), device="cpu")
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except EncoderWeightsError:
        raise
    except Exception as exc:  # noqa: BLE001 - a missing, damaged or code-carrying file
        raise EncoderWeightsError(f"{path}: cannot read encoder weights ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, dict) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
        raise EncoderWeightsError(f"{path}: not a state_dict (a mapping of names to tensors)")
    return state


def _misfit(want: dict[str, torch.Size], got: dict[str, torch.Tensor], where: str) -> list[str]:
    """What keeps ``got`` from loading into a module whose ``state_dict`` shapes are ``want``."""
    problems = []
    missing = sorted(set(want) - set(got))
    unexpected = sorted(set(got) - set(want))
    if missing:
        problems.append(f"missing keys {', '.join(where + k for k in missing)}")
    if unexpected:
        problems.append(f"unexpected keys {', '.join(where + k for k in unexpected)}")
    for key in sorted(set(want) & set(got)):
        if tuple(got[key].shape) != tuple(want[key]):
            problems.append(f"key {where}{key} has shape {tuple(got[key].shape)} in the file, {tuple(want[key])} in "
                            "the encoder")
    return problems


def trunk_states(encoder: ImageEncoder, state: dict[str, torch.Tensor],
                 path: str | Path = "the weights") -> dict[str, dict[str, torch.Tensor]]:
    """Each camera's trunk ``state_dict`` from a file's (the module docstring's two layouts), checked.

    :param encoder: the encoder
    :param state: the file's ``state_dict``
    :param path: the file, for the message
    :raises EncoderWeightsError: missing or unexpected keys, or a shape that differs (all named)
    """
    per_camera = any(key.split(".", 1)[0] in encoder.trunks for key in state)
    out, problems = {}, []
    for camera, trunk in encoder.trunks.items():
        want = {k: v.shape for k, v in trunk.state_dict().items()}
        if per_camera:
            mine = {k[len(camera) + 1:]: v for k, v in state.items() if k.startswith(camera + ".")}
            problems += _misfit(want, mine, camera + ".")
        else:  # (one trunk for all cameras: each problem named once)
            mine = state
            problems += [p for p in _misfit(want, mine, "") if p not in problems]
        out[camera] = mine
    if per_camera:
        stray = sorted(k for k in state if k.split(".", 1)[0] not in encoder.trunks)
        if stray:
            problems.append(f"unexpected keys {', '.join(stray)} (cameras: {', '.join(encoder.trunks)})")
    if problems:
        raise EncoderWeightsError(f"{path} does not fit the image encoder's trunk: " + "; ".join(problems))
    return out


def _encoders(target: nn.Module) -> list[ImageEncoder]:
    """Every distinct ImageEncoder in a module (a policy: the shared one and the target critic's)."""
    found: dict[int, ImageEncoder] = {}
    for module in target.modules():
        if isinstance(module, ImageEncoder):
            found.setdefault(id(module), module)
    return list(found.values())


def load_encoder_weights(target: nn.Module, path: str | Path, frozen: bool = False) -> list[ImageEncoder]:
    """Load a weights file into the trunks of every image encoder in ``target`` (an SB3 policy, or one
    :class:`ImageEncoder`); ``frozen``: then freeze them (:meth:`ImageEncoder.freeze`: ``requires_grad`` False,
    eval mode; an optimiser built before holds them but they get no gradient, so it leaves them as they are).
    A frozen model saved and loaded again is frozen only if built so (``frozen=True`` in its
    ``features_extractor_kwargs``, :func:`~khgrl.learner.image_policy.image_policy_kwargs`).

    :param target: a policy or an encoder
    :param path: the file (``torch.save`` of a ``state_dict``, or ``.safetensors``)
    :param frozen: freeze the trunks
    :return: the encoders loaded
    :raises EncoderWeightsError: no image encoder, or the file unreadable or not fitting (nothing loaded then)
    """
    encoders = _encoders(target)
    if not encoders:
        raise EncoderWeightsError(f"no image encoder in the {type(target).__name__} to load {path} into")
    state = read_weights(path)
    fitted = [trunk_states(encoder, state, path) for encoder in encoders]  # (all checked before any is loaded)
    for encoder, per_camera in zip(encoders, fitted):
        with torch.no_grad():
            for camera, trunk in encoder.trunks.items():
                trunk.load_state_dict(per_camera[camera])
        if frozen:
            encoder.freeze()
    return encoders
