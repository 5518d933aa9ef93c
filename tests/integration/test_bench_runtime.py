"""``khgrl bench runtime --quick`` runs to the end (issue 34, defect 8), in its quick form at small sizes: every
learner, actor and the router are real processes; the record's numbers come from them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from helpers import REPO

SIZES = ["--ingest-transitions", "4096", "--ingest-checkpoint-transitions", "4096", "--train-seconds", "2",
         "--actor-episodes", "1", "--episodes", "1", "--rt-priority", "0"]


@pytest.mark.integration
@pytest.mark.timeout(420)
def test_bench_runtime_quick_runs_to_the_end(tmp_path):
    """Before the fix the ingest learners ran with the default lead cap (``--max-lead 8`` + 2 batches of 8 = 24
    transitions) and refused every 256-transition batch the benchmark sends (``rejected over_lead``): the first
    ingest measurement never got an ack and the command hung (here: the subprocess timeout)."""
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "bench", "runtime", "--quick", *SIZES,
                           "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=380)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    record = json.loads(out.read_text())
    res = record["results"]
    for key in ("ingest", "ingest_signed", "ingest_journal", "ingest_ckpt"):  # every transition stored, none refused
        assert res[key]["learner_ingested"] == res[key]["transitions"] == 4096, res[key]
        assert res[key]["transitions_per_s"] > 0
    assert res["ingest_journal"]["durable_transitions_per_s"] > 0 and res["ingest_journal"]["learner_checkpoints"] >= 1
    train = res["train"]  # the learner trained from its backlog, next to standalone SB3 in the same run
    assert train["learner_window_grad_steps"] > 0 and train["standalone_train_calls"] >= 3 and train["ratio"] > 0
    assert res["actor"]["transitions"] > 0 and res["reference"]["env_steps"] > 0
    assert "learner ingest, no durability" in proc.stdout and "gradient steps/s" in proc.stdout
