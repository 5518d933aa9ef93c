"""Disk faults under a running learner: its checkpoint directory (``--checkpoint-dir``, a small tmpfs of its own)
turns read-only or full while an actor streams. Real processes over a real router: the learner keeps ingesting
and training, says why in its status, never acks as durable what neither the checkpoint nor the journal holds,
leaves no temporary directory behind, keeps the previous checkpoint, and once the disk is fixed the retried
checkpoint and the journal after it hold every transition the actor made exactly once (provenance). A final
checkpoint that fails ends the learner with 1 and a message, without a traceback. Faults come from ``mount``
(tests run as root here; chmod does not stop root).
(The same without processes: tests/unit/test_checkpoint.py.)
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import ProcGroup, read_json, unique_run, wait_for

FAST = ["--scenario", "low_cov", "--method", "khgrl", "--learning-starts", "16"]
LEARNER = ["--learning-starts", "16", "--checkpoint-every", "64", "--buffer-size", "20000"]
EPISODES = 7  # long enough for both faults in turn
STALE = "checkpoint.tmp-999999999"  # left by a learner killed while saving (no such PID: above pid_max)


def _mount(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["mount", *args], capture_output=True, text=True, timeout=30)


@pytest.fixture
def small_disk(tmp_path):
    """A 32 MiB tmpfs for the learner's checkpoints (unmounted afterwards)."""
    if os.name != "posix" or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs for the checkpoint directory needs root (CI runs these tests as root)")
    disk = tmp_path / "disk"
    disk.mkdir()
    res = _mount("-t", "tmpfs", "-o", "size=32m", "tmpfs", str(disk))
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({res.stderr.strip()}): the disk-fault tests need mount")
    try:
        yield disk
    finally:
        _mount("-o", "remount,rw", str(disk))
        if subprocess.run(["umount", str(disk)], capture_output=True, timeout=30).returncode != 0:
            subprocess.run(["umount", "-l", str(disk)], capture_output=True, timeout=30)


def _remount(disk: Path, options: str) -> None:
    """``mount -o remount,OPTIONS`` (a read-only remount waits while a save holds a file open for writing)."""
    deadline = time.monotonic() + 20
    while True:
        res = _mount("-o", f"remount,{options}", str(disk))
        if res.returncode == 0:
            return
        assert time.monotonic() < deadline, f"remount,{options}: {res.stderr}"
        time.sleep(0.05)


def _fill(disk: Path) -> Path:
    """Fill the filesystem up to the last block."""
    path = disk / "filler"
    with open(path, "wb", buffering=0) as fh:
        for size in (1 << 20, 4096):
            try:
                while True:
                    fh.write(b"\0" * size)
            except OSError:
                pass
    assert os.statvfs(disk).f_bavail == 0
    return path


class _Statuses:
    """The latest status of the learner, from a Zenoh subscriber in this process."""

    def __init__(self) -> None:
        self.learner = None

    def on(self, sample) -> None:
        from khgrl.common.wire.protocol import Status, decode

        self.learner = decode(Status, sample.payload.to_bytes()).info


def _checkpoint(ckpt_dir: Path) -> tuple[dict, dict[str, np.ndarray]]:
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    return read_json(ckpt_dir / "checkpoint" / "state.json"), load_checkpoint_arrays(ckpt_dir / "checkpoint")


def _assert_exactly_once(ckpt_dir: Path, actor: str, n: int) -> None:
    """The checkpoint's replay buffer and the journal after it (what a resumed learner replays) hold the actor's
    transitions 0..n-1, each once (provenance)."""
    from khgrl.learner.journal_scan import read_records

    state, arrays = _checkpoint(ckpt_dir)
    pos = state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]
    codes, steps = arrays["provenance_actor"][:pos], arrays["provenance_step"][:pos]
    assert np.all(codes >= 0), "an empty slot inside the filled part of the replay buffer"
    mine = [code for code, entry in enumerate(state["codes"]) if entry["actor"] == actor]
    got = steps[np.isin(codes, mine)].tolist()
    journal = [m for m in read_records(ckpt_dir / "journal", state["journal"]["next"]) if m.actor == actor]
    got += [m.first_step + i for m in journal for i in range(m.n)]
    assert sorted(got) == list(range(n)), f"{actor}: {len(got)} transitions held, not 0..{n - 1} exactly once"
    assert state["total_ingested"] + sum(m.n for m in journal) == n


def _durable_on_disk(ckpt_dir: Path, actor: str) -> int:
    """The highest seq of ``actor`` that the full checkpoint and the journal after it hold."""
    from khgrl.learner.journal_scan import read_records

    state = read_json(ckpt_dir / "checkpoint" / "state.json")
    held = state["actors"][actor]["next_seq"] - 1
    for msg in read_records(ckpt_dir / "journal", state["journal"]["next"]):
        if msg.actor == actor and msg.envelope.seq == held + 1:
            held += 1
    return held


def _temps(ckpt_dir: Path) -> list[str]:
    return sorted(p.name for p in ckpt_dir.glob("checkpoint.tmp-*"))


def _fault_and_fix(fault: str, disk: Path, ckpt_dir: Path, view: _Statuses, procs: list) -> None:
    """Break the disk while the actor streams, check what the learner does meanwhile, then fix the disk."""
    filler = _fill(disk) if fault == "full" else _remount(disk, "ro")
    reason = "ENOSPC" if fault == "full" else "EROFS"
    first = wait_for(lambda: view.learner if view.learner.checkpoint_error else None, 60, "a failed checkpoint",
                     procs=procs)
    assert first.checkpoint_error.startswith(reason), first.checkpoint_error
    saved = read_json(ckpt_dir / "checkpoint" / "state.json")
    assert first.durable["a0"] <= _durable_on_disk(ckpt_dir, "a0")  # acks say durable what checkpoint + journal hold
    # ingest and training go on, the failed save is retried (not at every turn), acks claim nothing new
    wait_for(lambda: (view.learner.checkpoint_failures > first.checkpoint_failures
                      and view.learner.ingested >= first.ingested + 64
                      and view.learner.iterations > first.iterations), 90, "ingest, training and a retry",
             procs=procs)
    during = view.learner
    assert during.checkpoint_error.startswith(reason) and during.checkpoints == first.checkpoints
    assert during.durable["a0"] == first.durable["a0"] < during.next_seq["a0"] - 1
    assert during.durable["a0"] <= _durable_on_disk(ckpt_dir, "a0")
    wait_for(lambda: not _temps(ckpt_dir), 20, "no temporary checkpoint directory (a retry may be writing one)")
    assert read_json(ckpt_dir / "checkpoint" / "state.json") == saved  # the previous checkpoint, intact
    _checkpoint(ckpt_dir)  # ... and readable
    if fault == "full":
        filler.unlink()
    else:
        _remount(disk, "rw")
    wait_for(lambda: view.learner.checkpoints > during.checkpoints and not view.learner.checkpoint_error, 90,
             "the retried checkpoint", procs=procs)
    assert view.learner.durable["a0"] > during.durable["a0"]


@pytest.mark.integration
@pytest.mark.timeout(480)
def test_learner_survives_a_broken_checkpoint_disk_and_loses_nothing(tmp_path, small_disk):
    """One run, both faults in turn (the disk full, fixed; then read-only, fixed), then a final checkpoint that
    fails."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.wire.protocol import Keys

    run, run_dir = unique_run("disk"), tmp_path / "run"
    ckpt_dir = small_disk / "ckpt"
    (ckpt_dir / STALE).mkdir(parents=True)
    (ckpt_dir / STALE / "replay_buffer.pkl").write_bytes(b"\0" * (4 << 20))
    view = _Statuses()
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, *LEARNER, "--checkpoint-dir", str(ckpt_dir))
        actor = g.actor(run, ep, *FAST, "--episodes", str(EPISODES), "--max-lead", "100000", "--rate", "40",
                        "--flush-timeout", "240")
        with open_client(ep, timeout=60) as s:
            sub = s.declare_subscriber(Keys(run).status("learner", "*"), view.on)
            try:
                wait_for(lambda: (ckpt_dir / "checkpoint" / "state.json").is_file() and view.learner, 180,
                         "a first checkpoint", procs=[learner, actor])
                assert STALE not in _temps(ckpt_dir)  # removed when the learner started
                for fault in ("full", "unwritable"):
                    assert actor.poll() is None, f"the actor finished before the fault {fault}: make it run longer"
                    _fault_and_fix(fault, small_disk, ckpt_dir, view, [learner, actor])
                assert actor.wait(240) == 0, actor.tail()
            finally:
                sub.undeclare()
        _remount(small_disk, "ro")  # the final checkpoint fails: exit 1 with one clear error, no traceback
        assert learner.stop(60) == 1, learner.tail()
        text = learner.text()
        assert "khgrl learner: error: the final checkpoint in" in text and "EROFS" in text, learner.tail()
        # the actor had flushed: its last batches are in the journal
        assert "the last checkpoint and the journal hold every transition received" in text
        assert "Traceback" not in text, learner.tail(60)
        # (the first failure may be the journal's write: "journal write failed (...)", then the snapshot's)
        assert " failed (" in text and "checkpoint recovered after" in text

    summary = read_json(run_dir / "actor-a0" / "summary.json")
    n = summary["transitions"]
    assert summary["episodes"] == EPISODES and summary["unconfirmed_transitions"] == 0
    assert summary["durable"] == summary["last_seq"]
    _assert_exactly_once(ckpt_dir, "a0", n)
    assert not _temps(ckpt_dir) and not (run_dir / "learner" / "checkpoint").exists()
