"""LeRobot datasets for the tests, made with LeRobot's own writer (``LeRobotDataset.create`` / ``add_frame`` /
``save_episode`` / ``finalize``): state-only, one float32 vector feature per frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_state_dataset", "load_with_library"]


def write_state_dataset(root: Path, episodes: list[np.ndarray], feature: str = "observation.state",
                        fps: int = 10, task: str = "test") -> Path:
    """Write ``episodes`` ((F_k, W) arrays) as a LeRobot dataset at ``root`` (which must not exist): ``feature``
    holds the rows, ``action`` a copy of their first column."""
    from khgrl.common.lerobot.library import lerobot_dataset_class

    width = episodes[0].shape[1]
    features = {feature: {"dtype": "float32", "shape": (width,), "names": [f"y{k}" for k in range(width)]},
                "action": {"dtype": "float32", "shape": (1,), "names": None}}
    ds = lerobot_dataset_class().create(repo_id=f"local/{root.name}", fps=fps, features=features, root=root,
                                        use_videos=False, video_backend="pyav")
    for ep in episodes:
        for row in np.asarray(ep, np.float32):
            ds.add_frame({feature: row, "action": row[:1].copy(), "task": task})
        ds.save_episode()
    ds.finalize()
    return root


def load_with_library(root: Path):
    """``LeRobotDataset(repo_id, root=root)``: LeRobot's own loader."""
    from khgrl.common.lerobot.library import lerobot_dataset_class

    return lerobot_dataset_class()(f"local/{root.name}", root=root, video_backend="pyav")
