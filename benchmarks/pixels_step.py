"""What camera observations cost per step of ``panda:pick``'s environment (issue 37): milliseconds per env step

* ``state``: ``panda:pick``'s :class:`~khgrl.common.tasks.panda.arm.PandaPosition` (no images);
* ``gym_hil_image_obs``: gym-hil's own ``image_obs=True`` path (``PandaPickCubeGymEnv(image_obs=True)`` in its
  ``EEActionWrapper``, both cameras at 128 x 128 with the model's render settings: shadow map 4096, 8 samples);
* ``pixels``: ``panda:pick-pixels``' :class:`~khgrl.common.tasks.panda.pixels.PandaPixels` (both cameras at
  128 x 128 through one cheap renderer: shadows and reflections off, no multisampling).

Each environment is reset with seed 0 and stepped ``--steps`` times with a zero displacement (the arm holds its
pose); reported per variant: median and mean ms per step (the reset not counted). One thread for torch
(``torch.set_num_threads(1)``; the project's rule for benchmarks on the shared machine).

    python -m khgrl.benchmarks.pixels_step --steps 10
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

__all__ = ["time_steps", "run_pixels_step_benchmark", "main"]


def time_steps(env, action: np.ndarray, steps: int) -> dict[str, float]:
    """Median and mean ms per ``env.step(action)`` over ``steps`` steps after ``env.reset(seed=0)``.

    :param env: a Gymnasium environment.
    :param action: the action of every step.
    :param steps: steps to time.
    """
    env.reset(seed=0)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        env.step(action)
        times.append(1e3 * (time.perf_counter() - t0))
    return {"median_ms": float(np.median(times)), "mean_ms": float(np.mean(times)), "steps": steps}


def _gym_hil_image_obs():
    """gym-hil's own image path: the base environment with ``image_obs=True`` in its ``EEActionWrapper``."""
    from khgrl.common.tasks.panda.arm import _headless_gl

    _headless_gl()
    from gym_hil.envs import PandaPickCubeGymEnv
    from gym_hil.wrappers.hil_wrappers import DEFAULT_EE_STEP_SIZE, EEActionWrapper

    base = PandaPickCubeGymEnv(random_block_position=False, image_obs=True)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*precision lowered by casting to float32.*")
        return EEActionWrapper(base, ee_action_step_size=DEFAULT_EE_STEP_SIZE, use_gripper=True)


def run_pixels_step_benchmark(steps: int = 10) -> dict[str, dict[str, float]]:
    """ms per step of the three variants (see the module docstring).

    :param steps: steps timed per variant.
    """
    from khgrl.common.tasks.panda.arm import PandaPosition
    from khgrl.common.tasks.panda.pixels import PandaPixels

    hold = np.array([0.490, 0.0, 0.078])  # where gym-hil's reset puts the pinch site: a still arm
    out = {}
    for name, make, action in (("state", PandaPosition, hold), ("pixels", PandaPixels, hold),
                               ("gym_hil_image_obs", _gym_hil_image_obs, np.zeros(4, np.float32))):
        env = make()
        try:
            out[name] = time_steps(env, action, steps)
        finally:
            env.close()
    return out


def main(argv: list[str] | None = None) -> None:
    """Print the benchmark's JSON.

    :param argv: command-line arguments (default: ``sys.argv``).
    """
    import torch

    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(prog="python -m khgrl.benchmarks.pixels_step", description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=10, help="steps timed per variant")
    args = parser.parse_args(argv)
    print(json.dumps(run_pixels_step_benchmark(args.steps), indent=2))


if __name__ == "__main__":
    main()
