"""The learner's training iterations do not fault their memory in again every time (learner/trainer.py
``keep_freed_memory``): measured in a fresh process, whose malloc starts with glibc's low thresholds."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

PROBE = r"""
import json, resource
import torch
torch.set_num_threads(1)
from khgrl.common.config.settings import TQCSettings
from khgrl.learner.trainer import build_model, keep_freed_memory

model = build_model(TQCSettings(learning_starts=0, device="cpu"), 0)
rb = model.replay_buffer
rb.observations[:2000] = 0.5
rb.actions[:2000] = 0.1
rb.pos = 2000
from stable_baselines3.common.logger import Logger
model.set_logger(Logger(folder=None, output_formats=[]))

def faults(iterations):
    out = []
    for _ in range(iterations):
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        model.train(gradient_steps=8, batch_size=256)
        out.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
    return out

before = faults(4)[1:]
kept = keep_freed_memory()
faults(1)
print(json.dumps({"before": before, "kept": kept, "after": faults(5)}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc")
def test_training_iterations_reuse_freed_memory():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["kept"] is True
    # glibc's defaults: the tensors of every iteration are mapped and faulted in anew (~10,000 pages); kept: a few
    # (the heap still grows now and then to a new peak: one iteration in five may fault its new pages in, so the
    # typical iteration -- the median -- is compared, before as after: a loaded machine once gave one iteration of
    # 911 faults among 9,808 and 13,101 before)
    typical = sorted(res["before"])[1]
    assert typical > 2000, res
    assert sorted(res["after"])[2] < typical / 10, res
