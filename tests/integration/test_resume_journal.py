"""A learner SIGKILLed and resumed at the default lead cap, and a damaged journal (issue 34, defects 1 and 2).
Real processes over a real router: one actor (kgrl, low_cov) and its learner, both at ``--max-lead 8`` (the
default, so the learner's lead cap is on), a full checkpoint, then batches in the journal after it, then the
learner is SIGKILLed. One module-scoped run serves every test: its run directory is copied at the kill, so that
the damage tests start from a real journal.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from helpers import ProcGroup, read_json, unique_run, wait_for

ACTOR = ["--scenario", "low_cov", "--method", "kgrl", "--learning-starts", "16", "--max-lead", "8",
         "--episodes", "2", "--id", "a0", "--flush-timeout", "90"]
# a full checkpoint every 200 transitions; the journal holds what came after the last one
LEARNER = ["--learning-starts", "16", "--max-lead", "8", "--checkpoint-every", "200"]
JOURNAL_ROWS = 48  # transitions in the journal after the full checkpoint when the learner is killed (cap: 24)


def _journal_after_checkpoint(ckpt_dir: Path) -> list:
    """The journal's records after the full checkpoint (what a resumed learner replays)."""
    from khgrl.learner.journal_scan import read_records

    state = read_json(ckpt_dir / "checkpoint" / "state.json")
    return list(read_records(ckpt_dir / "journal", state["journal"]["next"]))


@pytest.fixture(scope="module")
def killed_and_resumed(tmp_path_factory):
    """The run: a full checkpoint, then >= JOURNAL_ROWS transitions in the journal, SIGKILL (the run directory is
    copied then), ``--resume``, the actor's end, the learner stopped. Returns the paths, the learner's exit code and
    the copy taken at the kill."""
    from khgrl.benchmarks.scale import provenance_check

    tmp = tmp_path_factory.mktemp("resume")
    run, run_dir, at_kill = unique_run("rsm"), tmp / "run", tmp / "at-kill"
    ckpt_dir = run_dir / "learner"
    with ProcGroup(tmp) as g:
        ep = g.router()
        learner = g.learner(run, ep, *LEARNER)
        actor = g.actor(run, ep, *ACTOR)
        wait_for(lambda: sum(m.n for m in _journal_after_checkpoint(ckpt_dir)) >= JOURNAL_ROWS, 240,
                 "a full checkpoint, then the journal", procs=[learner, actor])
        learner.kill()
        learner.wait(30)
        shutil.copytree(run_dir, at_kill)
        replayed = _journal_after_checkpoint(at_kill / "learner")
        resumed = g.learner(run, ep, *LEARNER, "--resume")
        rc_actor = actor.wait(240)
        assert rc_actor == 0, actor.tail()
        rc = resumed.stop(60)
        log = resumed.text()
    return {"run_dir": run_dir, "at_kill": at_kill, "rc": rc, "log": log, "replayed": replayed,
            "check": provenance_check(run_dir), "tmp": tmp}


@pytest.mark.integration
@pytest.mark.timeout(600)
def test_a_resumed_learner_takes_up_the_actor_at_the_default_lead_cap(killed_and_resumed):
    """Issue 34, defect 1. Before the fix the journal replay stored batches without marking them for the lead
    count of the actor's stream: the replayed rows (>= 48 here, the cap is 8 + 2 x 8 = 24) counted as not covered
    by trained weights for good, every batch the actor sent was deferred, and the actor waited for the learner
    until its timeout (the fixture's ``actor.wait`` timed out; the transitions after the kill were unconfirmed)."""
    r = killed_and_resumed
    assert sum(m.n for m in r["replayed"]) >= JOURNAL_ROWS
    assert "journal: replayed" in r["log"], r["log"][-3000:]
    assert r["rc"] == 0, r["log"][-3000:]
    summary = read_json(r["run_dir"] / "actor-a0" / "summary.json")
    assert summary["episodes"] == 2 and summary["unconfirmed_transitions"] == 0, summary
    assert summary["durable"] == summary["last_seq"]
    check = r["check"]
    assert check["lost"] == 0 and check["duplicated"] == 0 and check["produced"] == summary["next_index"], check
