"""``python -m khgrl.benchmarks.image_learner`` (benchmarks/image_learner.py) on tiny images: it trains TQC with
the image encoder, trained and frozen, and writes its table's numbers as JSON."""

from __future__ import annotations

import json

import torch
from khgrl.benchmarks.image_learner import main


def test_the_image_learner_benchmark_times_tqc_steps_and_writes_json(tmp_path, capsys):
    threads = torch.get_num_threads()
    try:
        result = main(["--side", "32", "--batch-sizes", "4", "--seconds", "0", "--warmup", "0", "--fill", "16",
                       "--out", str(tmp_path / "out.json")])
    finally:
        torch.set_num_threads(threads)
    assert json.loads((tmp_path / "out.json").read_text()) == result
    cases = result["cases"]
    assert [(c["batch"], c["encoder"], c["steps"]) for c in cases] == [(4, "trained", 1), (4, "frozen", 1)]
    assert all(c["finite"] and c["steps_per_s"] > 0 and c["cpu_s_per_step"] > 0 for c in cases)
    assert cases[0]["actor_weights_mb"] > 0 and "frozen" in capsys.readouterr().out
