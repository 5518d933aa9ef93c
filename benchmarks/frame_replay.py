"""Memory and minibatch cost of the replay that stores each camera frame once
(:class:`~khgrl.learner.frame_replay.FrameReplayBuffer`, issue 37 point 3) against SB3's ``DictReplayBuffer``.

Observation: two ``128 x 128 x 3`` uint8 cameras and an 18-d float32 state; a 7-d action. The frame buffer of
``--transitions`` N slots is filled with 2 N transitions from 2 actors -- episodes of 100 steps, batches of 50,
actor 0 sending two batches to actor 1's one -- so it wraps and the per-actor shares evict (the result says the
shares). SB3's buffer of N slots gets N transitions (``add``, one at a time; its arrays are the same size whatever
it holds). For each, in a fresh process: bytes per transition (the frames alive and the per-slot arrays; SB3's
arrays), the resident memory the filled buffer added (``VmRSS`` of ``/proc/self/status`` after filling minus
before building it; every frame is written, so its pages are resident), and the wall time of ``sample(256)``
(median of ``--repeats``: indices, gather and the torch tensors). Both are extrapolated linearly to 100,000
transitions (the frame buffer's frames per transition: 1, 1/100 per episode start, the actors' pins).

Run (one torch thread)::

    python -m khgrl.benchmarks.frame_replay --transitions 5000 --out docs/frame_replay.json
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

__all__ = ["run_frame_replay_benchmark", "main"]

CAMERAS = ("pixels/front", "pixels/wrist")
TARGET = 100_000  # the transitions the extrapolation is for


def rss_bytes() -> int:
    """This process's resident memory (``VmRSS``) in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def _spaces(side: int, state: int, action: int) -> tuple[spaces.Dict, spaces.Box]:
    cam = spaces.Box(0, 255, (side, side, 3), np.uint8)
    obs = spaces.Dict({c: cam for c in CAMERAS} | {"state": spaces.Box(-10, 10, (state,), np.float32)})
    return obs, spaces.Box(-1, 1, (action,), np.float32)


class _Actor:
    """One actor's stream: frames drawn from a pool of random images (every frame is written in full)."""

    def __init__(self, code: int, pool: dict[str, np.ndarray], state: int, action: int, episode: int) -> None:
        self.code, self.pool, self.state, self.action, self.episode = code, pool, state, action, episode
        self.step = 0

    def batch(self, n: int) -> tuple[dict, dict, np.ndarray, np.ndarray, np.ndarray, dict]:
        steps = np.arange(self.step, self.step + n)
        t = steps % self.episode
        pick = (steps * 7 + self.code) % len(self.pool[CAMERAS[0]])
        obs = {c: self.pool[c][pick] for c in CAMERAS}
        nxt = {c: self.pool[c][(pick + 7) % len(self.pool[c])] for c in CAMERAS}
        obs["state"] = np.full((n, self.state), 0.5, np.float32)
        nxt["state"] = obs["state"] + 0.1
        done = t == self.episode - 1
        kw = dict(intervened=np.zeros(n, np.uint8), clipped=np.zeros(n, np.uint8), actor=self.code,
                  first_step=self.step)
        self.step += n
        return obs, nxt, np.zeros((n, self.action), np.float32), np.zeros(n, np.float32), done, kw


def _time_sample(rb: Any, batch: int, repeats: int) -> float:
    """Median seconds of ``rb.sample(batch)``."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        rb.sample(batch)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _pool(side: int, seed: int) -> dict[str, np.ndarray]:
    """61 random frames per camera that the actors' observations are drawn from."""
    rng = np.random.default_rng(seed)
    return {c: rng.integers(0, 256, (61, side, side, 3), dtype=np.uint8) for c in CAMERAS}


def _in_child(case: str, *args: Any) -> dict[str, Any]:
    """Run a case in a fresh process (spawned): its resident memory is its own, not what an earlier case left
    with the allocator."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as ex:
        return ex.submit(_case, case, *args).result()


def _case(case: str, n: int, side: int, state: int, action: int, batch: int, repeats: int,
          seed: int) -> dict[str, Any]:
    import torch

    torch.set_num_threads(1)
    np.random.seed(seed)
    obs, act = _spaces(side, state, action)
    return (_frame_case if case == "frame_replay" else _sb3_case)(n, obs, act, _pool(side, seed), batch, repeats)


def _frame_case(n: int, obs: spaces.Dict, act: spaces.Box, pool: dict, batch: int, repeats: int) -> dict[str, Any]:
    from khgrl.learner.frame_replay import FrameReplayBuffer  # (imported before the memory is measured)

    gc.collect()
    before = rss_bytes()
    rb = FrameReplayBuffer(n, obs, act, device="cpu", min_episode_steps=100, max_streams=2)
    state, action = obs["state"].shape[0], act.shape[0]
    actors = [_Actor(0, pool, state, action, 100), _Actor(1, pool, state, action, 100)]
    t0, added = time.perf_counter(), 0
    while added < 2 * n:
        for actor in (actors[0], actors[0], actors[1]):  # actor 0 sends twice as much
            o, x, a, r, d, kw = actor.batch(50)
            rb.add_batch(o, x, a, r, d, d.copy(), **kw)
            added += 50
    fill_s = time.perf_counter() - t0
    rss = rss_bytes() - before
    slots = sum(a.nbytes for a in (rb.observations, rb.next_observations, rb.actions, rb.rewards, rb.dones,
                                   rb.timeouts, rb.obs_frame, rb.next_frame, *rb.side_arrays().values()))
    used = rb.store.live * rb.store.frame_bytes + slots
    out = dict(transitions=n, added=added, fill_s=fill_s, live_frames=rb.store.live,
               frame_capacity=rb.store.capacity, frames_per_transition=rb.store.live / n,
               bytes_per_transition=used / n, allocated_bytes=rb.nbytes(), rss_bytes=rss,
               rss_per_transition=rss / n, sample_s=_time_sample(rb, batch, repeats), shares=rb.shares())
    del rb
    gc.collect()
    return out


def _sb3_case(n: int, obs: spaces.Dict, act: spaces.Box, pool: dict, batch: int, repeats: int) -> dict[str, Any]:
    from stable_baselines3.common.buffers import DictReplayBuffer

    gc.collect()
    before = rss_bytes()
    rb = DictReplayBuffer(n, obs, act, device="cpu", n_envs=1)
    actor = _Actor(0, pool, obs["state"].shape[0], act.shape[0], 100)
    t0 = time.perf_counter()
    for _ in range(n // 50):
        o, x, a, r, d, _kw = actor.batch(50)
        for i in range(50):
            rb.add({k: v[i:i + 1] for k, v in o.items()}, {k: v[i:i + 1] for k, v in x.items()}, a[i:i + 1],
                   r[i:i + 1], d[i:i + 1], [{"TimeLimit.truncated": bool(d[i])}])
    fill_s = time.perf_counter() - t0
    rss = rss_bytes() - before
    arrays = [*rb.observations.values(), *rb.next_observations.values(), rb.actions, rb.rewards, rb.dones,
              rb.timeouts]
    used = sum(a.nbytes for a in arrays)
    out = dict(transitions=n, added=n // 50 * 50, fill_s=fill_s, bytes_per_transition=used / n, rss_bytes=rss,
               rss_per_transition=rss / n, sample_s=_time_sample(rb, batch, repeats))
    del rb
    gc.collect()
    return out


def run_frame_replay_benchmark(transitions: int = 5000, side: int = 128, state: int = 18, action: int = 7,
                               batch: int = 256, repeats: int = 30, seed: int = 0,
                               out: str | None = None) -> dict[str, Any]:
    """Fill both buffers, measure, print a table and the extrapolation to 100,000 transitions.

    :param transitions: slots of each buffer (a multiple of 50)
    :param side: image side in pixels
    :param state: state vector size
    :param action: action size
    :param batch: minibatch size timed
    :param repeats: samples timed per buffer
    :param seed: the pixel pool's and the sampling's seed
    :param out: also write the results as JSON here
    """
    import torch

    args = (transitions, side, state, action, batch, repeats, seed)
    frame, sb3 = _in_child("frame_replay", *args), _in_child("sb3_dict", *args)
    extra = {name: {"bytes": r["bytes_per_transition"] * TARGET, "rss_bytes": r["rss_per_transition"] * TARGET}
             for name, r in (("frame_replay", frame), ("sb3_dict", sb3))}
    result = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
                          "load_average": list(os.getloadavg()), "threads": 1},
              "setup": {"side": side, "cameras": len(CAMERAS), "state": state, "action": action,
                        "episode_steps": 100, "batch_rows": 50, "actors": 2, "sample_batch": batch,
                        "repeats": repeats},
              "frame_replay": frame, "sb3_dict": sb3,
              "extrapolated": {"transitions": TARGET, "linear_from": transitions, **extra}}
    _print(result)
    if out:
        Path(out).write_text(json.dumps(result, indent=2) + "\n")
    return result


def _print(result: dict[str, Any]) -> None:
    s = result["setup"]
    print(f"{s['cameras']} cameras {s['side']}x{s['side']}x3 + {s['state']}-d state, episodes of "
          f"{s['episode_steps']}, 2 actors; load average {result['machine']['load_average'][0]:.1f}")
    head = ("buffer", "slots", "added", "bytes/tr", "RSS MB", "RSS/tr", "sample ms", "fill s")
    print(" ".join(f"{h:>12}" for h in head))
    for name in ("frame_replay", "sb3_dict"):
        r = result[name]
        cells = (name, r["transitions"], r["added"], f"{r['bytes_per_transition']:,.0f}",
                 f"{r['rss_bytes'] / 1e6:,.0f}", f"{r['rss_per_transition']:,.0f}", f"{r['sample_s'] * 1e3:.2f}",
                 f"{r['fill_s']:.1f}")
        print(" ".join(f"{c:>12}" for c in cells))
    f = result["frame_replay"]
    print(f"frame replay: {f['live_frames']} frames alive ({f['frames_per_transition']:.3f} per transition, "
          f"capacity {f['frame_capacity']}), shares {f['shares']}")
    e = result["extrapolated"]
    for name in ("frame_replay", "sb3_dict"):
        print(f"extrapolated linearly from {e['linear_from']} to {e['transitions']:,} transitions, {name}: "
              f"{e[name]['bytes'] / 1e9:.2f} GB of arrays, {e[name]['rss_bytes'] / 1e9:.2f} GB resident")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """The command line (``--help``).

    :param argv: arguments (None: ``sys.argv``)
    """
    p = argparse.ArgumentParser(prog="python -m khgrl.benchmarks.frame_replay", description=__doc__.split("\n")[0])
    p.add_argument("--transitions", type=int, default=5000, help="slots of each buffer (default: %(default)s)")
    p.add_argument("--side", type=int, default=128, help="image side in pixels (default: %(default)s)")
    p.add_argument("--batch", type=int, default=256, help="minibatch timed (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=30, help="samples timed (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="(default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    a = p.parse_args(argv)
    if a.transitions % 50 or a.transitions < 100:
        p.error("--transitions: a multiple of 50, at least 100")
    return run_frame_replay_benchmark(a.transitions, a.side, batch=a.batch, repeats=a.repeats, seed=a.seed,
                                      out=a.out)


if __name__ == "__main__":
    main()
