"""The third-party client example (deploy/examples/drag_client.py: only zenoh + msgpack) against a real router,
learner and actor: its corrections land in the learner's replay buffer as intervened transitions."""

from __future__ import annotations

import ast
import csv
import sys

import pytest

from helpers import REPO, ProcGroup, read_json, unique_run

CLIENT = REPO / "deploy" / "examples" / "drag_client.py"
STEPS = 30


def test_client_imports_only_zenoh_msgpack_and_the_stdlib():
    tree = ast.parse(CLIENT.read_text())
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            mods.add((node.module or "").split(".")[0])
    third = {m for m in mods if m not in sys.stdlib_module_names}
    assert third == {"zenoh", "msgpack"}, mods


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_drag_client_corrections_land_in_the_replay_buffer(tmp_path):
    from learner.service import load_checkpoint_arrays

    run, run_dir = unique_run("drag"), tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "100000", run_dir=run_dir)
        actor = g.actor(run, ep, "--scenario", "low_cov", "--method", "khgrl", "--episodes", "2", "--rate", "50",
                        "--learning-starts", "16", "--max-lead", "100000", run_dir=run_dir)
        client = g.start("drag", [sys.executable, str(CLIENT), "--connect", ep, "--run", run, "--actor", "a0",
                                  "--episode", "1", "--start", "10", "--steps", str(STEPS)])
        assert client.wait(150) == 0, client.tail()
        assert f"held P_h for {STEPS} frames" in client.tail()
        assert actor.wait(150) == 0, actor.tail()
        learner.stop(30)
    with open(run_dir / "actor-a0" / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    iv_steps = sum(int(r["intervention_steps"]) for r in rows)
    assert STEPS - 2 <= iv_steps <= STEPS + 2, rows  # one step per frame held (give or take the first and release)
    with open(run_dir / "actor-a0" / "corrections.csv", newline="") as fh:
        rec = list(csv.DictReader(fh))
    assert len(rec) == iv_steps and {r["client"] for r in rec} == {"drag"}
    summary = read_json(run_dir / "actor-a0" / "summary.json")
    assert summary["corrections"]["holds"] == 1 and summary["corrections"]["releases"] == 1, summary["corrections"]
    ck = run_dir / "learner" / "checkpoint"
    state, arrays = read_json(ck / "state.json"), load_checkpoint_arrays(ck)
    n = state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]
    assert n == sum(int(r["steps"]) for r in rows)
    assert int(arrays["intervened"][:n].sum()) == iv_steps
    # the actor's per-episode TensorBoard scalars carry the intervention statistics
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "actor-a0" / "tb"))
    acc.Reload()
    tb = {k: [e.value for e in acc.Scalars(k)] for k in acc.Tags()["scalars"]}
    assert sum(tb["interventions/steps"]) == iv_steps and len(tb["episode/return"]) == len(rows)
    assert sum(tb["interventions/count"]) == sum(int(r["interventions"]) for r in rows)
    assert tb["interventions/mean_abs_xi_h"] == pytest.approx([float(r["mean_abs_xi_h"]) for r in rows], rel=1e-5)
    clipped = [int(r["clipped_steps"]) / int(r["intervention_steps"]) if int(r["intervention_steps"]) else 0.0
               for r in rows]
    assert tb["interventions/clipped_fraction"] == pytest.approx(clipped, rel=1e-5)
