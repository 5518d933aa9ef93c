"""LeRobot's dataset library, imported on demand: the one place KhGRL imports it (``pip install 'khgrl[lerobot]'``).

KhGRL reads and writes LeRobot datasets (format v3.0) with LeRobot's own code, from the ``lerobot-dataset`` package
(LeRobot 0.4.4's ``lerobot.datasets`` as the module ``ledataset``; the full ``lerobot`` needs Python >= 3.12 from
0.5 on and pins torch < 2.11). Nothing here is imported unless a LeRobot path is used.

**torchvision.** ``ledataset`` imports torchvision at import time (``datasets/utils.py``: ``from torchvision import
transforms``; ``datasets/video_utils.py``: ``import torchvision``) without declaring it. The only use on a dataset
without images or videos is none; on an image dataset, ``transforms.ToTensor`` in ``hf_transform_to_torch``.
Where torchvision imports, it is used as is. Where it is missing or broken (PyPI's torchvision fails beside a torch
it was not built for: ``RuntimeError: operator torchvision::nms does not exist``), :func:`_install_torchvision_shim`
puts a minimal ``torchvision`` module in ``sys.modules`` holding only ``transforms.ToTensor`` (a faithful one:
HWC uint8 image -> CHW float32 in [0, 1]) and logs it at debug level (the README says it once: a notice before every
LeRobot command was noise); any other torchvision attribute (the
torchvision video decoder) raises an ImportError naming the shim. KhGRL's datasets are state-only.

**numpy >= 2.4.** LeRobot stores a per-frame scalar (``next.reward``, ``next.done``: shape (1,)) as a (1,) array,
and the ``datasets`` version it pins (< 4.2) encodes it with ``float(value)``, which numpy 2.4 refuses for a 1-D
array ("only 0-dimensional arrays can be converted to Python scalars"; numpy < 2.4 allowed it with a
DeprecationWarning). Where numpy refuses it, :func:`_install_scalar_fix` wraps ``datasets.Value.encode_example`` so
that a (1,) array is encoded as its one element -- what it did with numpy < 2.4 -- and logs one line saying so.

**Offline.** ``HF_HUB_OFFLINE=1`` is set before the library is imported, and :func:`open_dataset` checks that the
folder holds ``meta/info.json`` before LeRobot's loader sees it (the loader would otherwise create the folder and
ask the Hugging Face hub for it).
"""

from __future__ import annotations

import importlib.machinery
import logging
import os
import sys
import types
from pathlib import Path
from typing import Any

__all__ = ["LeRobotMissing", "NotADataset", "INSTALL_HINT", "lerobot_dataset_class", "open_dataset", "quiet",
           "INTERVENTION",
           "REWARD", "DONE", "STATE", "ACTION"]

INSTALL_HINT = "pip install 'khgrl[lerobot]'"
# LeRobot's names (lerobot/utils/constants.py: OBS_STATE, ACTION, REWARD, DONE). The intervention flag is the one
# LeRobot's HIL-SERL actor puts in each transition's complementary_info (lerobot/rl/actor.py, key
# TeleopEvents.IS_INTERVENTION.value = "is_intervention", lerobot/teleoperators/utils.py) and its ReplayBuffer writes
# as the dataset feature "complementary_info.<key>" (lerobot/rl/buffer.py, to_lerobot_dataset).
STATE, ACTION, REWARD, DONE = "observation.state", "action", "next.reward", "next.done"
INTERVENTION = "complementary_info.is_intervention"
_log = logging.getLogger(__name__)


class LeRobotMissing(ImportError):
    """LeRobot's dataset library is not installed."""


class _ToTensor:
    """torchvision's ``transforms.ToTensor``: a PIL image or (H, W, C) array -> (C, H, W) float tensor.

    uint8 values are divided by 255 (to [0, 1]); other dtypes are kept as they are, as torchvision does. A 2-D
    image gets one channel.
    """

    def __call__(self, pic: Any):
        import numpy as np
        import torch

        arr = np.array(pic, copy=True)
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim != 3:
            raise TypeError(f"ToTensor: expected an (H, W) or (H, W, C) image, got shape {arr.shape}")
        tensor = torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1)))
        if tensor.dtype == torch.uint8:
            return tensor.to(torch.float32).div(255.0)
        return tensor

    def __repr__(self) -> str:
        return "ToTensor()"


def _unavailable(module: str):
    def __getattr__(name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        raise ImportError(f"{module}.{name}: torchvision is not usable here; KhGRL's stand-in "
                          f"(khgrl.common.lerobot.library) has only transforms.ToTensor (state and image datasets, no "
                          f"torchvision video decoding)")
    return __getattr__


def _install_torchvision_shim(reason: str) -> None:
    """Put a ``torchvision`` with only ``transforms.ToTensor`` in ``sys.modules`` (see the module docstring).

    :param reason: why the real one could not be imported (logged).
    """
    for name in [n for n in sys.modules if n == "torchvision" or n.startswith("torchvision.")]:
        del sys.modules[name]  # what a failed import left behind
    tv = types.ModuleType("torchvision")
    tr = types.ModuleType("torchvision.transforms")
    tv.__spec__ = importlib.machinery.ModuleSpec("torchvision", None, is_package=True)
    tr.__spec__ = importlib.machinery.ModuleSpec("torchvision.transforms", None)
    tr.ToTensor = _ToTensor
    tr.__getattr__ = _unavailable("torchvision.transforms")
    tv.transforms = tr
    tv.__getattr__ = _unavailable("torchvision")
    tv.__khgrl_shim__ = True
    sys.modules["torchvision"], sys.modules["torchvision.transforms"] = tv, tr
    _log.debug("torchvision unusable (%s): LeRobot's dataset code runs with KhGRL's minimal stand-in "
                 "(transforms.ToTensor only; state datasets need nothing else)", reason)


def _ensure_torchvision() -> None:
    import datasets  # noqa: F401 - first: its config looks for torchvision (find_spec) and must see the real state

    try:
        import torchvision  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - missing (ImportError) or built for another torch (RuntimeError)
        _install_torchvision_shim(f"{type(exc).__name__}: {exc}".splitlines()[0])


def _install_scalar_fix() -> None:
    """Let ``datasets.Value`` encode a (1,) array as its element where numpy refuses ``float()`` of one."""
    import numpy as np
    from datasets.features import features as hf_features

    try:
        float(np.ones(1))
        return  # numpy < 2.4: nothing to do
    except TypeError:
        pass
    value_cls = hf_features.Value
    if getattr(value_cls.encode_example, "__khgrl_fix__", False):
        return
    original = value_cls.encode_example

    def encode_example(self, value):
        if isinstance(value, np.ndarray) and value.shape == (1,):
            value = value[0]
        return original(self, value)

    encode_example.__khgrl_fix__ = True
    value_cls.encode_example = encode_example
    _log.info("numpy %s refuses float() of a (1,) array: datasets.Value encodes LeRobot's (1,) features by their "
              "element (khgrl.common.lerobot.library)", np.__version__)


def _ledataset_module():
    os.environ["HF_HUB_OFFLINE"] = "1"  # KhGRL reads and writes local folders only: never the Hugging Face hub
    try:
        import ledataset  # noqa: F401
    except ImportError:
        raise LeRobotMissing(f"LeRobot datasets need LeRobot's dataset library: {INSTALL_HINT}") from None
    _ensure_torchvision()
    _install_scalar_fix()
    from ledataset.datasets import lerobot_dataset

    return lerobot_dataset


def lerobot_dataset_class():
    """LeRobot's ``LeRobotDataset`` (``ledataset.datasets.lerobot_dataset``).

    :raises LeRobotMissing: the library is not installed (the message says how to install it).
    """
    return _ledataset_module().LeRobotDataset


class NotADataset(ValueError):
    """A folder that LeRobot's loader cannot read as a dataset."""


def open_dataset(path: str | Path):
    """Load the local LeRobot dataset in folder ``path`` with LeRobot's own loader (offline; nothing is created).

    :param path: the dataset's folder (the one holding ``meta/info.json``).
    :raises NotADataset: no such folder, no ``meta/info.json``, or the library refuses it (its reason given).
    :raises LeRobotMissing: the library is not installed.
    """
    root = Path(path)
    if not root.is_dir():
        raise NotADataset(f"{root}: no such LeRobot dataset folder")
    if not (root / "meta" / "info.json").is_file():
        raise NotADataset(f"{root}: not a LeRobot dataset (no meta/info.json; LeRobot's v3.0 format has meta/, "
                          f"data/ and videos/)")
    dataset_class = lerobot_dataset_class()
    quiet()
    try:
        return dataset_class(f"local/{root.name}", root=root, video_backend="pyav")
    except Exception as exc:  # noqa: BLE001 - whatever the library raises on a folder it cannot read
        text = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
        raise NotADataset(f"{root}: LeRobot's loader cannot read it as a dataset ({text})") from None


def quiet() -> None:
    """No per-episode "Map" progress bars from ``datasets`` (KhGRL shows its own progress)."""
    import datasets

    datasets.disable_progress_bars()
