"""The learner's gradient step on camera observations (issue 37): sb3-contrib TQC with the DrQ image encoder
(:mod:`khgrl.learner.image_policy`), trained and frozen trunk, on the CPU with one torch thread, for each batch size.

The observation is two ``128 x 128 x 3`` uint8 cameras and an 18-d state (``--side``, ``--cameras``, ``--state``);
the action 7-d. The replay buffer (SB3's ``DictReplayBuffer``) is filled with ``--fill`` random transitions; each
case times SB3's own ``train(gradient_steps=1)`` after ``--warmup`` untimed steps, repeated until ``--seconds``
have passed (at least one step): wall-clock steps/s, and the process's CPU time per step (less sensitive to other
load on a shared machine, with one thread). Also reported: the policy's parameters and the size of what an actor
receives (the ``actor`` network's ``state_dict``, the encoder included), in float32.

Per gradient step SB3's ``train()`` runs each camera's batch through an encoder 5 times (the actor on the
observations and the next observations, the target critic on the next observations, the critic on the
observations for its loss, with a backward pass, and for the actor's loss): this is what the numbers cost.

Run::

    python -m khgrl.benchmarks.image_learner --batch-sizes 256 64 --seconds 5 --out image_learner.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["run_image_learner_benchmark", "spaces_env", "main"]


def spaces_env(side: int, cameras: int, state: int, action: int) -> Any:
    """A gymnasium env with the benchmark's spaces (never stepped: SB3 needs an env to build a model).

    :param side: image side in pixels
    :param cameras: how many cameras
    :param state: the state vector's size
    :param action: the action's size
    """
    import gymnasium as gym
    from gymnasium import spaces

    names = ["front", "wrist", *(f"cam{i}" for i in range(2, cameras))][:cameras]
    obs = {name: spaces.Box(0, 255, (side, side, 3), np.uint8) for name in names}
    obs["state"] = spaces.Box(-1, 1, (state,), np.float32)

    class Spaces(gym.Env):
        observation_space = spaces.Dict(obs)
        action_space = spaces.Box(-1, 1, (action,), np.float32)

        def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
            super().reset(seed=seed)
            return self.observation_space.sample(), {}

        def step(self, act: Any) -> tuple[Any, float, bool, bool, dict]:
            return self.observation_space.sample(), 0.0, False, False, {}

    return Spaces()


def _fill(buffer: Any, n: int, rng: np.random.Generator) -> None:
    """``n`` random transitions written straight into a DictReplayBuffer's arrays."""
    for store in (buffer.observations, buffer.next_observations):
        for key, array in store.items():
            if array.dtype == np.uint8:
                array[:n] = rng.integers(0, 256, array[:n].shape, dtype=np.uint8)
            else:
                array[:n] = rng.uniform(-1, 1, array[:n].shape)
    buffer.actions[:n] = rng.uniform(-1, 1, buffer.actions[:n].shape)
    buffer.rewards[:n] = rng.standard_normal(buffer.rewards[:n].shape)
    buffer.pos, buffer.full = n, False


def _case(env: Any, batch: int, frozen: bool, fill: int, warmup: int, seconds: float, seed: int) -> dict[str, Any]:
    """One case: a fresh TQC model, its buffer filled, SB3's ``train`` timed."""
    import torch
    from khgrl.learner.image_policy import tqc_image_policy
    from sb3_contrib import TQC
    from stable_baselines3.common.logger import Logger

    policy, kwargs = tqc_image_policy(env.observation_space, frozen=frozen)
    model = TQC(policy, env, policy_kwargs={**kwargs, "net_arch": [256, 256]}, buffer_size=fill, batch_size=batch,
                learning_starts=0, seed=seed, device="cpu")
    model.set_logger(Logger(None, []))
    _fill(model.replay_buffer, fill, np.random.default_rng(seed))
    for _ in range(warmup):
        model.train(gradient_steps=1, batch_size=batch)
    steps, start, cpu = 0, time.perf_counter(), time.process_time()
    while steps == 0 or time.perf_counter() - start < seconds:
        model.train(gradient_steps=1, batch_size=batch)
        steps += 1
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    actor = model.policy.actor.state_dict()
    return {"batch": batch, "encoder": "frozen" if frozen else "trained", "steps": steps, "seconds": elapsed,
            "steps_per_s": steps / elapsed, "s_per_step": elapsed / steps,
            "cpu_s_per_step": cpu / steps,
            "policy_params": sum(p.numel() for p in model.policy.parameters()),
            "actor_weights_mb": sum(v.numel() for v in actor.values()) * 4 / 1e6,
            "finite": bool(all(torch.isfinite(p).all() for p in model.policy.parameters()))}


def run_image_learner_benchmark(batch_sizes: tuple[int, ...] = (256, 64), seconds: float = 5.0, warmup: int = 1,
                                side: int = 128, cameras: int = 2, state: int = 18, action: int = 7,
                                fill: int = 512, frozen: tuple[str, ...] = ("trained", "frozen"), seed: int = 0,
                                threads: int = 1, out: str | None = None) -> dict[str, Any]:
    """Time TQC's gradient step with the image encoder for each batch size and encoder mode; print a table.

    :param batch_sizes: minibatch sizes
    :param seconds: time each case at least this long (at least one step)
    :param warmup: untimed steps first
    :param side: image side in pixels
    :param cameras: how many cameras
    :param state: state vector size
    :param action: action size
    :param fill: transitions in the replay buffer
    :param frozen: encoder modes, ``trained`` and/or ``frozen``
    :param seed: the models' and the data's seed
    :param threads: torch threads
    :param out: also write the results as JSON here
    """
    import torch

    torch.set_num_threads(threads)
    env = spaces_env(side, cameras, state, action)
    rows = [_case(env, b, mode == "frozen", fill, warmup, seconds, seed) for b in batch_sizes for mode in frozen]
    result = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                          "cpus": os.cpu_count(), "load_average": list(os.getloadavg()),
                          "torch": torch.__version__, "threads": threads},
              "setup": {"side": side, "cameras": cameras, "state": state, "action": action, "fill": fill,
                        "warmup": warmup, "seconds": seconds, "algo": "tqc", "net_arch": [256, 256]},
              "cases": rows}
    print(f"TQC + DrQ encoder, {cameras} x {side}x{side}x3 + {state}-d state, CPU, {threads} thread(s), "
          f"load average {os.getloadavg()[0]:.1f}")
    head = ("batch", "encoder", "steps", "steps/s", "s/step", "cpu s/step", "params", "actor MB")
    print(" ".join(f"{h:>10}" for h in head))
    for r in rows:
        cells = (r["batch"], r["encoder"], r["steps"], f"{r['steps_per_s']:.3f}", f"{r['s_per_step']:.2f}",
                 f"{r['cpu_s_per_step']:.2f}", f"{r['policy_params']:,}", f"{r['actor_weights_mb']:.1f}")
        print(" ".join(f"{c:>10}" for c in cells))
    if out:
        Path(out).write_text(json.dumps(result, indent=2))
    return result


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """The command line (``--help``).

    :param argv: arguments (None: ``sys.argv``)
    """
    p = argparse.ArgumentParser(prog="python -m khgrl.benchmarks.image_learner", description=__doc__.split("\n")[0])
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[256, 64], help="(default: %(default)s)")
    p.add_argument("--seconds", type=float, default=5.0, help="time per case, at least 1 step (default: %(default)s)")
    p.add_argument("--warmup", type=int, default=1, help="untimed steps per case (default: %(default)s)")
    p.add_argument("--side", type=int, default=128, help="image side in pixels (default: %(default)s)")
    p.add_argument("--cameras", type=int, default=2, help="(default: %(default)s)")
    p.add_argument("--state", type=int, default=18, help="state vector size (default: %(default)s)")
    p.add_argument("--action", type=int, default=7, help="action size (default: %(default)s)")
    p.add_argument("--fill", type=int, default=512, help="transitions in the buffer (default: %(default)s)")
    p.add_argument("--encoder", nargs="+", choices=["trained", "frozen"], default=["trained", "frozen"],
                   help="encoder modes (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="(default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the results as JSON here (default: none)")
    a = p.parse_args(argv)
    return run_image_learner_benchmark(tuple(a.batch_sizes), a.seconds, a.warmup, a.side, a.cameras, a.state,
                                       a.action, a.fill, tuple(a.encoder), a.seed, a.threads, a.out)


if __name__ == "__main__":
    main()
