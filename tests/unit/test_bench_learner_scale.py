"""``khgrl bench scale`` and ``khgrl bench learner`` without a run: the children's environment keeps the caller's
``PYTHONPATH``, the learner's training seconds come from its closing log line, and ``--device`` reaches
``khgrl up``."""

from __future__ import annotations

import math
import os

from khgrl.benchmarks import scale
from khgrl.benchmarks.cli import build_parser


def test_children_keep_the_callers_pythonpath(monkeypatch, tmp_path):
    """Failed before (issue 39): ``PYTHONPATH`` was replaced by the repository's root, so packages installed with
    ``--target`` (or a task module on the caller's path) were gone for ``khgrl up``'s children."""
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    monkeypatch.setenv("KHGRL_TEST_MARK", "kept")
    env = scale.child_env()
    parts = env["PYTHONPATH"].split(os.pathsep)
    assert str(tmp_path) in parts and str(scale.REPO) in parts
    assert env["KHGRL_TEST_MARK"] == "kept"
    monkeypatch.delenv("PYTHONPATH")
    assert scale.child_env()["PYTHONPATH"] == str(scale.REPO)


def test_training_seconds_from_the_learners_closing_line(tmp_path):
    assert scale._train_seconds(tmp_path) != scale._train_seconds(tmp_path)  # (NaN: no log)
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "learner.log").write_text(
        "x INFO learner learner done: {'transitions': 224, 'iterations': 16, 'train_s': 8.8, 'version': 16}\n")
    assert scale._train_seconds(tmp_path) == 8.8


def test_scale_takes_the_learners_device():
    args = build_parser().parse_args(["scale", "--device", "cuda", "--actors", "1", "8", "14"])
    assert args.device == "cuda" and args.actors == [1, 8, 14]



def test_images_bench_refuses_bad_settings_and_counts_resident_bytes(capsys):
    from khgrl.benchmarks.cli import main
    from khgrl.benchmarks.images import _bytes_per_transition

    assert main(["images", "--rate", "0"]) == 2 and "--rate 0.0" in capsys.readouterr().err
    case = {"rss_mb_series": [300.0, 310.0, 400.0], "produced": 1024}
    assert _bytes_per_transition(case) == 100 * 2**20 / 1024
    assert math.isnan(_bytes_per_transition({"rss_mb_series": [300.0], "produced": 5}))
