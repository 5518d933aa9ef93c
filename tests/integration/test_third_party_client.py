"""The third-party client example (deploy/examples/drag_client.py: only zenoh + msgpack) against a real router,
learner and actor: its corrections land in the learner's replay buffer as intervened transitions."""

from __future__ import annotations

import ast
import csv
import importlib.util
import sys

import numpy as np
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


def test_client_speaks_the_typed_protocol_both_ways():
    """Our frames (with ``last``) parse in the client; its corrections decode as typed Correction messages."""
    from khgrl.common.wire.protocol import Correction, Frame, ProtocolError, decode, encode

    spec = importlib.util.spec_from_file_location("drag_client", CLIENT)
    client = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(client)
    p = np.array([0.25, 0.5])
    frame = Frame(actor="a0", episode=2, t=7, phase=0.1, robot=p, desired=p, mean=p, scale=np.array([1.0, 1.0]),
                  intervening=False, task="passage-low_cov", ret=-1.0, next_mean=p, last=True)
    assert client.parse_frame(encode(frame, "a0", 7)) == {"episode": 2, "t": 7, "mean": [0.25, 0.5], "last": True}
    assert client.parse_frame(encode(frame.replace(last=None), "a0", 8))["last"] is False
    assert client.parse_frame(b"\xc1") is None
    hold = decode(Correction, client.envelope("correction", "drag", 0, client="drag", actor="a0", active=True,
                                              p_h=[0.25, 0.55], episode=2, t=7))
    assert (hold.client, hold.actor, hold.active, hold.episode, hold.t) == ("drag", "a0", True, 2, 7)
    np.testing.assert_allclose(hold.p_h, [0.25, 0.55])
    release = decode(Correction, client.envelope("correction", "drag", 1, client="drag", actor="a0", active=False))
    assert release.active is False and release.p_h is None
    payload = client.envelope("correction", "drag", 2, client="drag", actor="a0", active=False)
    assert b"\xa1v\x01" in payload
    with pytest.raises(ProtocolError):  # the schema version is the integer 1: true is refused
        decode(Correction, payload.replace(b"\xa1v\x01", b"\xa1v\xc3"))


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_drag_client_corrections_land_in_the_replay_buffer(tmp_path):
    from khgrl.learner.checkpoint import load_checkpoint_arrays

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
    arrays = load_checkpoint_arrays(run_dir / "learner" / "checkpoint")
    filled = arrays["provenance_actor"] >= 0  # the slots the run filled
    assert int(filled.sum()) == sum(int(r["steps"]) for r in rows)
    assert int(arrays["intervened"][filled].sum()) == iv_steps
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
