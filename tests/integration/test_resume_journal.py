"""A learner SIGKILLed and resumed at the default lead cap, and a damaged journal (issue 34, defects 1 and 2).
Real processes over a real router: one actor (kgrl, low_cov) and its learner, both at ``--max-lead 8`` (the
default, so the learner's lead cap is on), a full checkpoint, then batches in the journal after it, then the
learner is SIGKILLed. One module-scoped run serves every test: its run directory is copied at the kill, so that
the damage tests start from a real journal.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from helpers import REPO, ProcGroup, python_main, read_json, unique_run, wait_for

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
        shutil.copytree(run_dir, at_kill, copy_function=_copy_if_there)  # (the actor still writes its folder)
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


def _damage(run_dir: Path, kind: str) -> tuple[str, int]:
    """Damage the journal segment after the full checkpoint of a copied run: a bit flipped inside its second
    record's body, or the file cut in the middle of a record past its first half. Returns the file and the offset
    of the damaged record."""
    from khgrl.learner.journal_scan import JournalScan

    ckpt = run_dir / "learner"
    start = read_json(ckpt / "checkpoint" / "state.json")["journal"]["next"]
    where = [(rec.file, rec.offset) for rec in JournalScan(ckpt / "journal", start).records()]
    assert len(where) >= 6 and len({name for name, _ in where}) == 1, where
    name, off = where[1] if kind == "bitflip" else where[len(where) // 2]
    path = ckpt / "journal" / name
    data = bytearray(path.read_bytes())
    if kind == "bitflip":
        data[off + 80] ^= 0x04
    else:
        del data[off + 30:]
    path.write_bytes(bytes(data))
    return name, off


def _learner_argv(run: str, ep: str, run_dir: Path, *extra: str) -> list[str]:
    return python_main("khgrl.learner.main") + ["--run", run, "--connect", ep, "--run-dir", str(run_dir), *LEARNER,
                                                 "--resume", *extra]


def _copy_if_there(src: str, dst: str) -> None:
    """Copy a file of a live run, unless it was renamed or removed since it was listed (the actor's files)."""
    try:
        shutil.copy2(src, dst)
    except FileNotFoundError:
        pass


@pytest.mark.integration
@pytest.mark.timeout(300)
@pytest.mark.parametrize("kind", ["bitflip", "truncate"])
def test_a_damaged_journal_is_refused_or_its_loss_accepted_and_counted(killed_and_resumed, tmp_path, kind):
    """Issue 34, defect 2. Before the fix a flipped bit mid-segment or a truncated segment read as "a write cut
    short": the resumed learner ignored the rest of the segment, skipped the confirmed batches it lacked ("a0 no
    longer holds batches ...: skipping them") and ended with exit 0 -- here the first `--resume` started and ran
    instead of refusing (the 120 s subprocess timeout), and `--accept-journal-loss` did not exist."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Ack, Keys, decode

    run_dir = tmp_path / "run"
    shutil.copytree(killed_and_resumed["at_kill"], run_dir)
    name, off = _damage(run_dir, kind)
    files = {p.name: p.read_bytes() for p in (run_dir / "learner" / "journal").iterdir()}
    run = unique_run("dmg")
    acks: list = []
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        refused = subprocess.run(_learner_argv(run, ep, run_dir), cwd=REPO, capture_output=True, text=True,
                                 timeout=120)
        assert refused.returncode == 2, refused.stdout[-3000:] + refused.stderr
        lines = refused.stderr.strip().splitlines()
        assert len(lines) == 1 and f"{name} at byte {off}" in lines[0] and "--accept-journal-loss" in lines[0], lines
        assert "confirmed batches affected: a0 " in lines[0], lines
        assert {p.name: p.read_bytes() for p in (run_dir / "learner" / "journal").iterdir()} == files  # untouched
        with open_client(ep) as s:
            sub = s.declare_subscriber(Keys(run).ack("a0"), lambda m: acks.append(decode(Ack, m.payload.to_bytes())))
            try:
                learner = g.start("learner", _learner_argv(run, ep, run_dir, "--accept-journal-loss"))
                wait_for(lambda: acks, 120, "the accepting learner's ack", procs=[learner])
                rc = learner.stop(60)
            finally:
                sub.undeclare()
        text = learner.text()
    state = read_json(run_dir / "learner" / "checkpoint" / "state.json")
    lost = state["actors"]["a0"]["skipped"]
    assert rc == 3 and "batches confirmed durable before this learner resumed are lost" in text, text[-3000:]
    if kind == "bitflip":  # a hole: stepped over, counted, the stream goes on after it
        assert lost >= 1 and acks[0].received == state["actors"]["a0"]["next_seq"] - 1
    else:  # a tail: the ack's received is where the journal ends, so that a0 re-sends what it still holds
        assert acks[0].received < killed_and_resumed["replayed"][-1].envelope.seq
    assert "'lost_batches': 0" not in text and "resuming without them (--accept-journal-loss)" in text
