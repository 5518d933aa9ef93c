"""An actor refuses weights that are not its network's before copying them (issue 21): a valid 60 MB weights
message (under the protocol's 64 MiB limit) cost an actor +190 MB and a 271 ms stall; now its length alone refuses
it, through the real decode path, while the largest honest message (every tensor, 4,096 actor ids in ``trained``)
still fits."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
from khgrl.actor.weights import WeightsReceiver
from khgrl.common.wire.checks import RejectCounter
from khgrl.common.wire.messages import Weights
from khgrl.common.wire.protocol import encode


def _receiver() -> WeightsReceiver:
    from khgrl.common.config.settings import RunConfig
    from khgrl.common.tasks.api import load_task
    from khgrl.common.tasks.kgrl_env import KGRLEnv
    from khgrl.learner.algorithm import algorithm_class

    cfg = RunConfig()
    env = KGRLEnv(load_task(cfg.task_spec, None), seed=0)
    policy = algorithm_class("tqc").actor_policy(env.observation_space, env.action_space, cfg.tqc)
    return WeightsReceiver(None, policy.weights_template(), RejectCounter("actor/a0"), "k")


def test_oversized_weights_are_refused_before_decoding_and_honest_ones_fit():
    rx = _receiver()
    real = {k: np.full(shape, 0.5, np.float32) for k, shape in rx.template.items()}
    ids = {f"{i:04d}" + "x" * 60: 10**12 for i in range(4096)}  # the most a trained map can hold
    honest = encode(Weights(version=7, trained=ids, tensors=real, epoch="e" * 64), "learner", 1)
    assert len(honest) <= rx.max_bytes < 2 * len(honest) + 2**20
    item = rx.parse(honest)
    assert item.version == 7 and set(item.state_dict) == set(rx.template)

    big = encode(Weights(version=8, trained={}, tensors={"big": np.zeros(15_000_000, np.float32)}, epoch="e"),
                 "learner", 2)
    assert 55e6 < len(big) < 64 * 2**20  # valid for the protocol
    tracemalloc.start()
    try:
        t0 = time.perf_counter()
        rx.offer(big)
        dt = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert rx.ready is None and rx.rejects.counts["weights"] == 1
    assert peak < 1e6, f"refusing it allocated {peak / 1e6:.1f} MB"  # the old path: +75 MB here (+190 MB RSS)
    assert dt < 0.05, f"refusing it took {dt * 1e3:.0f} ms"  # the old path: ~100 ms here (271 ms measured)

    # the right size but not this network's tensors: refused by names/shapes before the float32 copy
    wrong = {k: np.zeros(tuple(reversed(v.shape)), np.float32) for k, v in real.items()}
    rx.offer(encode(Weights(version=9, trained={}, tensors=wrong, epoch="e"), "learner", 3))
    assert rx.ready is None and rx.rejects.counts["weights"] == 2
