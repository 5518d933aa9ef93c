"""A quick correctness check of the CUDA-graph learner on a GPU (``python -m khgrl.benchmarks.gpu_check``; part of
``benchmarks/gpu_check.sh``): the learner's TQC (real sizes) with each gradient step a replayed CUDA graph, against

* the same iterations with the step function called eagerly, capturable Adam alike (the graph replays what the
  step does: the parameters' largest difference after 4 iterations);
* SB3's own ``train()`` on the same device (``--no-cuda-graph``: the difference, for information -- Adam's
  capturable form rounds differently);

then a rollback (a NaN planted in a critic weight: the iteration's fault is found, the snapshot restored in place,
and the graph trains on), and a checkpoint of the graphed learner loaded on the CPU and on the GPU, each training
an iteration. On a machine without a GPU (``--device cpu``) the graphed learner is the eager one: a dry run of the
checks' own code. Prints one JSON document (and writes it to ``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

__all__ = ["run_checks", "main"]

OBS, ACT, SIZE = 32, 3, 4000
TASK = SimpleNamespace(out_dim=ACT, obs_low=[-10.0] * OBS, obs_high=[10.0] * OBS)


def _learner(device: str, graph: bool, algo: str = "tqc", seed: int = 0):
    """The learner's ``algo`` on ``device`` with a filled buffer; ``graph``: CUDA graphs where the device has them,
    else the same iteration eager (capturable Adam on cuda either way)."""
    from khgrl.common.config.settings import TQCSettings
    from khgrl.learner.cuda_graph import GraphedTrainer, set_capturable
    from khgrl.learner.trainer import build_algorithm
    from stable_baselines3.common.logger import configure

    on_gpu = device.startswith("cuda")
    learner = build_algorithm(TQCSettings(device=device, learning_starts=0, cuda_graph=graph and on_gpu), seed,
                              TASK, algo)
    learner.model.set_logger(configure(None, []))
    if graph and learner.graphed is None:
        learner.graphed = GraphedTrainer(learner.model, graph=False)
        if on_gpu:
            set_capturable(learner.model, True)
    rng = np.random.default_rng(1)
    f32 = np.float32
    learner.store(rng.normal(size=(SIZE, OBS)).astype(f32), rng.normal(size=(SIZE, OBS)).astype(f32),
                  rng.uniform(-1, 1, (SIZE, ACT)).astype(f32), rng.normal(size=SIZE).astype(f32),
                  (np.arange(SIZE) % 100 == 99).astype(f32), np.zeros(SIZE, f32),
                  intervened=np.zeros(SIZE, np.uint8), clipped=np.zeros(SIZE, np.uint8), actor=0, first_step=0)
    return learner


def _iterations(learner, n: int, seed: int = 3) -> None:
    import torch

    np.random.seed(seed)
    torch.manual_seed(seed)
    for it in range(n):
        learner.train(8, timestep=SIZE + 8 * it, sample_limit=None)


def _diff(a, b) -> float:
    sa, sb = a.model.policy.state_dict(), b.model.policy.state_dict()
    return max((sa[k].float() - sb[k].float()).abs().max().item() for k in sa)


def run_checks(device: str) -> dict:
    """The checks (module docstring) on ``device``; returns their results (``ok`` overall)."""
    import torch

    res: dict = {"device": device, "torch": torch.__version__}
    if device.startswith("cuda"):
        res["gpu"] = torch.cuda.get_device_name()
    t0 = time.perf_counter()
    graphed, eager, sb3 = _learner(device, True), _learner(device, True), _learner(device, False)
    if graphed.graphed is not None and eager.graphed is not None and device.startswith("cuda"):
        from khgrl.learner.cuda_graph import GraphedTrainer

        eager.graphed = GraphedTrainer(eager.model, graph=False)  # (capturable Adam, called eagerly)
    for learner in (graphed, eager, sb3):
        _iterations(learner, 4)
    res["graph_vs_eager_step_max_abs"] = _diff(graphed, eager)
    res["graph_vs_sb3_train_max_abs"] = _diff(graphed, sb3)
    res["captures"] = getattr(graphed.graphed, "captures", 0)
    res["losses"] = {k: graphed.model.logger.name_to_value.get(f"train/{k}") for k in
                     ("actor_loss", "critic_loss", "ent_coef_loss", "ent_coef")}
    # rollback: a NaN planted in a critic weight
    snap = graphed.snapshot()
    before = {k: v.clone() for k, v in graphed.model.policy.state_dict().items()}
    with torch.no_grad():
        next(graphed.model.critic.parameters()).view(-1)[0] = float("nan")
    try:  # (as the trainer's iteration: eager, torch's distribution check raises on the NaN; graphed, it is off)
        graphed.train(8, timestep=SIZE + 100, sample_limit=None)
    except (ValueError, RuntimeError) as exc:
        res["nan_raised"] = type(exc).__name__
    res["nan_fault"] = graphed.fault()
    graphed.restore(snap)
    res["restored_exactly"] = all(torch.equal(before[k], v) for k, v in graphed.model.policy.state_dict().items())
    graphed.train(8, timestep=SIZE + 108, sample_limit=None)
    res["fault_after_restore"] = graphed.fault()
    # checkpoint: loads on the CPU and on the device, trains there
    from khgrl.common.config.settings import TQCSettings
    from khgrl.learner.tqc import TQCAlgorithm

    with tempfile.TemporaryDirectory() as tmp:
        graphed.save(Path(tmp))
        for where in dict.fromkeys(("cpu", device)):
            loaded = TQCAlgorithm.load(Path(tmp), TASK, TQCSettings(device=where, learning_starts=0), where)
            from stable_baselines3.common.logger import configure

            loaded.model.set_logger(configure(None, []))
            loaded.train(8, timestep=SIZE + 200, sample_limit=None)
            res[f"checkpoint_trains_on_{where}"] = loaded.fault() is None
    res["seconds"] = round(time.perf_counter() - t0, 1)
    res["ok"] = bool(res["graph_vs_eager_step_max_abs"] <= 1e-4 and res["nan_fault"] and res["restored_exactly"]
                     and res["fault_after_restore"] is None
                     and all(v for k, v in res.items() if k.startswith("checkpoint_trains_on_")))
    return res


def main(argv: list[str] | None = None) -> int:
    """Run the checks; exit 0 when all hold, 1 otherwise."""
    p = argparse.ArgumentParser(prog="python -m khgrl.benchmarks.gpu_check", description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda", help="torch device (default: %(default)s)")
    p.add_argument("--out", default=None, help="also write the JSON here (default: none)")
    args = p.parse_args(argv)
    res = run_checks(args.device)
    text = json.dumps(res, indent=2, default=str)
    print(text)
    if args.out:
        Path(args.out).write_text(text)
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
