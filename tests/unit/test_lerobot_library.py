"""The import of LeRobot's dataset code (its torchvision stand-in, the missing-library message) and the all-or-nothing
writer."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from khgrl.common.lerobot import library
from khgrl.common.lerobot.writer import Episode, write_dataset

from lerobot_data import load_with_library

FEATURES = {"observation.state": {"dtype": "float32", "shape": (2,), "names": None},
            "next.reward": {"dtype": "float32", "shape": (1,), "names": None}}


def test_to_tensor_stand_in_is_torchvisions() -> None:
    img = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3) * 14  # H = 2, W = 3, C = 3
    out = library._ToTensor()(img)
    assert tuple(out.shape) == (3, 2, 3) and str(out.dtype) == "torch.float32"
    np.testing.assert_allclose(out.numpy(), img.transpose(2, 0, 1) / 255.0, rtol=1e-6)
    assert float(out.max()) <= 1.0
    grey = library._ToTensor()(np.full((4, 5), 255, np.uint8))
    assert tuple(grey.shape) == (1, 4, 5) and float(grey.min()) == 1.0


def test_the_stand_in_only_where_torchvision_fails() -> None:
    library.lerobot_dataset_class()
    tv = sys.modules["torchvision"]
    try:
        import importlib.util

        real = importlib.util.find_spec("torchvision").loader is not None
    except (ImportError, ValueError):
        real = False
    assert getattr(tv, "__khgrl_shim__", False) != real
    if not real:
        with pytest.raises(ImportError, match="torchvision is not usable here"):
            tv.io.VideoReader  # noqa: B018 - anything beyond ToTensor says what it is


def test_missing_library_names_the_extra(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "ledataset", None)  # as if not installed
    with pytest.raises(library.LeRobotMissing, match=r"pip install 'khgrl\[lerobot\]'"):
        library.lerobot_dataset_class()


def test_writer_is_all_or_nothing(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    good = Episode("t", {"observation.state": np.ones((3, 2), np.float32),
                         "next.reward": np.arange(3, dtype=np.float32)[:, None]})
    bad = Episode("t", {"observation.state": np.ones((3, 5), np.float32),  # not the declared shape
                        "next.reward": np.zeros((3, 1), np.float32)})
    with pytest.raises(ValueError, match="observation.state"):
        write_dataset(out, fps=5, features=FEATURES, episodes=[good, bad])
    assert list(tmp_path.iterdir()) == []  # neither OUT nor the temporary folder
    write_dataset(out, fps=5, features=FEATURES, episodes=[good], sidecar={"run": "r"})
    with pytest.raises(FileExistsError, match="--overwrite"):
        write_dataset(out, fps=5, features=FEATURES, episodes=[good, good])
    with pytest.raises(ValueError):
        write_dataset(out, fps=5, features=FEATURES, episodes=[bad], overwrite=True)
    ds = load_with_library(out)  # the first dataset is still there, whole
    assert ds.num_episodes == 1 and ds.num_frames == 3 and (out / "meta" / "khgrl.json").is_file()
    np.testing.assert_array_equal(np.asarray(ds.hf_dataset.with_format("numpy")["next.reward"]), [0, 1, 2])


def test_lerobots_loader_imports_in_this_environment_without_a_notice():
    """Before: every LeRobot command began with a torchvision warning on stderr (the stand-in's notice)."""
    import subprocess
    import sys

    code = ("from khgrl.common.lerobot.library import lerobot_dataset_class; "
            "print(lerobot_dataset_class().__name__)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "LeRobotDataset", proc.stderr
    assert "torchvision" not in proc.stderr, proc.stderr
