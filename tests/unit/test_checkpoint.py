"""Learner checkpoints under disk faults, without processes: a failed save leaves the previous checkpoint and no
temporary directory, leftovers of killed learners are removed at start, the loop keeps training, marks nothing
durable, retries with backoff, shows the fault in its status and recovers; the launcher's view shows it.
(Real processes on a full and a read-only filesystem: tests/integration/test_disk_faults.py.)"""

from __future__ import annotations

import errno
import io
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import khgrl.learner.durability as loop_module  # (where the loop's checkpoints are saved)
import numpy as np
import pytest
from khgrl.common.config.settings import TQCSettings
from khgrl.common.process import StopFlag
from khgrl.common.wire.messages import LearnerInfo
from khgrl.common.wire.protocol import Ack, Status, Transitions, decode, encode
from khgrl.learner.checkpoint import (
    TMP_PREFIX,
    find_checkpoint,
    load_checkpoint_arrays,
    remove_stale_temps,
    save_checkpoint,
)
from khgrl.learner.disk_faults import RETRY_MAX_S, SaveFaults, fault_reason, is_disk_fault
from khgrl.learner.loop import LearnerLoop, open_learner

SMALL = TQCSettings(learning_starts=16, buffer_size=1000, net_arch=(32, 32), batch_size=32)
ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/data/checkpoint.tmp-1/replay_buffer.pkl")


def _batch(seq: int, n: int = 8) -> Transitions:
    rng = np.random.default_rng(seq)
    obs = rng.uniform(0, 1, (n, 5)).astype(np.float32)
    msg = Transitions(actor="a0", first_step=n * seq, obs=obs, next_obs=obs[::-1].copy(),
                      action=rng.uniform(-1, 1, (n, 2)).astype(np.float32), reward=np.ones(n, np.float32),
                      terminated=np.zeros(n, np.uint8), truncated=np.zeros(n, np.uint8),
                      intervened=np.zeros(n, np.uint8), clipped=np.zeros(n, np.uint8), base_seq=0, stream="s0",
                      task="0123456789abcdef")
    return decode(Transitions, encode(msg, "a0", seq))


class _Pub:
    queries = 0

    def __init__(self) -> None:
        self.sent: list = []

    def _keep(self, msg) -> None:
        encode(msg, "learner", len(self.sent))  # as a receiver would check it
        self.sent.append(msg)

    weights = ack = status = _keep

    def of(self, cls) -> list:
        return [m for m in self.sent if isinstance(m, cls)]


class _FakeModel:
    """Writes small files where the learner algorithm would write its own; ``fail_buffer`` makes the buffer a disk
    fault."""

    def __init__(self, fail_buffer: OSError | None = None) -> None:
        self.fail_buffer = fail_buffer

    def save(self, directory: Path) -> list[Path]:
        (Path(directory) / "model.zip").write_bytes(b"model")
        (Path(directory) / "replay_buffer.pkl").write_bytes(b"half a buffer")
        if self.fail_buffer is not None:
            raise self.fail_buffer
        return [Path(directory) / "model.zip", Path(directory) / "replay_buffer.pkl"]


def _entries(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


# ------------------------------------------------------------------------------------ learner/checkpoint.py
def test_a_failed_save_leaves_the_previous_checkpoint_and_no_temporary_directory(tmp_path):
    save_checkpoint(tmp_path, _FakeModel(), {"mark": 1})
    with pytest.raises(OSError) as caught:
        save_checkpoint(tmp_path, _FakeModel(fail_buffer=ENOSPC), {"mark": 2})
    assert is_disk_fault(caught.value)
    assert _entries(tmp_path) == ["checkpoint"]
    ck = find_checkpoint(tmp_path)
    assert json.loads((ck / "state.json").read_text())["mark"] == 1 and (ck / "replay_buffer.pkl").read_bytes() == \
        b"half a buffer"  # (the fake's bytes of the first, complete save)
    # with only the checkpoint.old/ a crash between the renames leaves, a failed save keeps that one
    os.rename(tmp_path / "checkpoint", tmp_path / "checkpoint.old")
    with pytest.raises(OSError):
        save_checkpoint(tmp_path, _FakeModel(fail_buffer=ENOSPC), {"mark": 3})
    assert _entries(tmp_path) == ["checkpoint.old"] and find_checkpoint(tmp_path) == tmp_path / "checkpoint.old"
    # and a save that succeeds replaces it only once the new one is in place
    assert save_checkpoint(tmp_path, _FakeModel(), {"mark": 4}) == tmp_path / "checkpoint"
    assert _entries(tmp_path) == ["checkpoint"]
    assert json.loads((tmp_path / "checkpoint" / "state.json").read_text())["mark"] == 4


def test_leftover_temporary_checkpoints_of_dead_learners_are_removed(tmp_path):
    save_checkpoint(tmp_path, _FakeModel(), {"mark": 1})
    (tmp_path / "checkpoint.old").mkdir()
    (tmp_path / "checkpoint.old" / "state.json").write_text("{}")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)  # exited: its PID is not running (unless reused at once)
    live_pid = os.getppid()
    for pid in (dead_pid, os.getpid(), live_pid):
        d = tmp_path / f"{TMP_PREFIX}{pid}"
        d.mkdir()
        (d / "model.zip").write_bytes(b"x" * 1000)
    (tmp_path / f"{TMP_PREFIX}junk").write_bytes(b"")  # not a PID, not a directory: removed too
    removed = remove_stale_temps(tmp_path)
    assert sorted(p.name for p in removed) == sorted(f"{TMP_PREFIX}{p}" for p in (dead_pid, os.getpid(), "junk"))
    assert _entries(tmp_path) == ["checkpoint", "checkpoint.old", f"{TMP_PREFIX}{live_pid}"]
    assert remove_stale_temps(tmp_path / "nowhere") == []


def test_open_learner_cleans_the_checkpoint_dir_and_resumes_from_it(tmp_path):
    ckpt_dir = tmp_path / "data"
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    loop = LearnerLoop(trainer, streams, _Pub(), learner_id="L", learner_dir=tmp_path / "learner",
                       checkpoint_every=0, flag=StopFlag(), checkpoint_dir=ckpt_dir)
    loop.offer(_batch(0))
    assert loop.checkpoint() == ckpt_dir / "checkpoint"
    assert find_checkpoint(tmp_path / "learner") is None
    (ckpt_dir / f"{TMP_PREFIX}999999999").mkdir()  # no such PID
    trainer, _ = open_learner(SMALL, 1, tmp_path / "learner", resume=True, logger_formats=("csv",),
                              checkpoint_dir=ckpt_dir)
    assert trainer.total == 8 and _entries(ckpt_dir) == ["checkpoint"]


def test_khgrl_up_resume_looks_in_the_checkpoint_dir(tmp_path):
    from khgrl.deploy.run.rundir import has_checkpoint

    save_checkpoint(tmp_path / "data", _FakeModel(), {"mark": 1})
    assert not has_checkpoint(tmp_path / "run") and has_checkpoint(tmp_path / "run", str(tmp_path / "data"))
    # a learner killed before its first full checkpoint left its journal: that is resumed too
    (tmp_path / "run" / "learner" / "journal").mkdir(parents=True)
    (tmp_path / "run" / "learner" / "journal" / "segment-000000.bin").write_bytes(b"")
    assert has_checkpoint(tmp_path / "run")


def test_save_faults_back_off_and_log_once_per_reason(caplog):
    now = [100.0]
    faults = SaveFaults(lambda: now[0])
    assert faults.ready() and faults.error == ""
    delays = []
    with caplog.at_level(logging.WARNING, logger="khgrl.learner"):
        for _ in range(8):
            delays.append(faults.failed(ENOSPC, 40))
            assert not faults.ready()
            now[0] += delays[-1]
            assert faults.ready()
        assert delays == [1, 2, 4, 8, 16, RETRY_MAX_S, RETRY_MAX_S, RETRY_MAX_S]
        assert faults.error == fault_reason(ENOSPC) == \
            "ENOSPC No space left on device: /data/checkpoint.tmp-1/replay_buffer.pkl"
        assert faults.failures == faults.streak == 8
        warned = [r.getMessage() for r in caplog.records]
        # the first (at 0 s), then once a minute at most: at 61 s of the streak (tries at 0 1 3 7 15 31 61 91 s)
        assert len(warned) == 2 and "ENOSPC" in warned[0] and "40 transitions are not durable" in warned[0]
        faults.failed(OSError(errno.EROFS, os.strerror(errno.EROFS)), 40)  # a new reason: logged at once
        assert len(caplog.records) == 3 and faults.error == "EROFS Read-only file system"
        faults.succeeded()
        assert "recovered after 9 failed attempts" in caplog.records[-1].getMessage()
    assert faults.ready() and faults.error == "" and faults.streak == 0 and faults.failures == 9
    assert is_disk_fault(RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed"))
    assert not is_disk_fault(ValueError("a bug")) and not is_disk_fault(RuntimeError("a bug"))


# ------------------------------------------------------------------------------------ learner/loop.py
def test_loop_survives_a_failing_checkpoint_and_recovers(tmp_path, monkeypatch):
    now = [0.0]
    pub = _Pub()
    trainer, streams = open_learner(SMALL, 1, tmp_path / "learner", resume=False, logger_formats=("csv",))
    loop = LearnerLoop(trainer, streams, pub, learner_id="L", learner_dir=tmp_path / "learner", checkpoint_every=32,
                       flag=StopFlag(), clock=lambda: now[0])
    for seq in range(4):
        loop.offer(_batch(seq))
    loop.step()
    assert loop.durable.checkpoints == 1 and pub.of(Ack)[-1].durable == 3
    first = find_checkpoint(tmp_path / "learner")
    real_save = loop_module.save_checkpoint
    attempts = []

    def broken(*args, **kw):
        attempts.append(now[0])
        raise ENOSPC

    monkeypatch.setattr(loop_module, "save_checkpoint", broken)
    for seq in range(4, 8):  # 32 more transitions: a checkpoint is due and fails; ingest and training go on
        loop.offer(_batch(seq))
        loop.step()
    assert attempts == [0.0] and loop.trainer.total == 64 and loop.trainer.iterations >= 2
    assert pub.of(Ack)[-1].received == 7 and all(a.durable <= 3 for a in pub.of(Ack))  # never more than is saved
    info = loop.info()
    assert info.checkpoint_error.startswith("ENOSPC") and info.checkpoint_failures == 1 and info.checkpoints == 1
    decode(Status, encode(Status(role="learner", info=info), "L", 0))  # valid on the wire
    while now[0] < 8.0:  # retried after 1 s, then 2 s, then 4 s (not at every turn)
        now[0] += 0.25
        loop.step()
    assert attempts == [0.0, 1.0, 3.0, 7.0] and loop.durable.saves.failures == 4
    assert all(a.durable <= 3 for a in pub.of(Ack))
    assert json.loads((first / "state.json").read_text())["total_ingested"] == 32  # the previous one, intact
    monkeypatch.setattr(loop_module, "save_checkpoint", real_save)  # the disk is fixed
    now[0] = 15.0  # the retry after 8 s is due
    loop.step()
    assert loop.durable.checkpoints == 2 and pub.of(Ack)[-1].durable == 7
    assert loop.info().checkpoint_error == "" and loop.info().checkpoint_failures == 4
    arrays = load_checkpoint_arrays(find_checkpoint(tmp_path / "learner"))
    assert arrays["provenance_step"][:64].tolist() == list(range(64))

    monkeypatch.setattr(loop_module, "save_checkpoint", lambda *a, **k: (_ for _ in ()).throw(ValueError("a bug")))
    with pytest.raises(ValueError):  # not a disk fault: raised, as before
        loop.checkpoint()


# ------------------------------------------------------------------------------------ deploy/run/progress.py
def _learner_info(**kw) -> LearnerInfo:
    base = dict(id="learner", epoch="e", ingested=120, iterations=15, gradient_steps=96, grad_steps_per_s=12.4,
                version=3, pending_iterations=0, queue_depth=0, rejects={}, paused=False, checkpoints=2,
                next_seq={}, durable={}, duplicates={}, weights_queries=0)
    info = LearnerInfo(**{**base, **kw})
    return decode(Status, encode(Status(role="learner", info=info), "learner", 1)).info


def test_progress_view_shows_a_failing_checkpoint(capsys):
    from khgrl.deploy.run.progress import ProgressView
    from rich.console import Console

    failing = _learner_info(checkpoint_error="EROFS Read-only file system: /data/[x]", checkpoint_failures=3)
    live = ProgressView(["a0"], 2, enabled=True)
    live.learner = failing
    console = Console(width=300, record=True, file=io.StringIO())
    console.print(live._table())
    text = console.export_text()
    assert "CHECKPOINT FAILING (3 failed saves): EROFS Read-only file system: /data/[x]" in text
    assert "learner: 120 transitions" in text

    plain = ProgressView(["a0"], 2, enabled=False)
    for info in (_learner_info(), failing, failing, _learner_info(checkpoint_failures=3)):
        plain.status(Status(role="learner", info=info))
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0].startswith("[learner] CHECKPOINT FAILING (3 failed saves): EROFS")
    assert lines[1] == "[learner] checkpoint recovered (2 saved)"
    assert plain.caption() == "learner: 120 transitions, 96 gradient steps (12/s), weights v3"


# ------------------------------------------------------------------------------------ learner/main.py
def test_a_failed_final_checkpoint_is_one_clear_error(capsys):
    from types import SimpleNamespace

    from khgrl.learner.main import _final_checkpoint_failed

    lost = {"n": 60}
    loop = SimpleNamespace(ckpt_dir=Path("/data/ck"), durable=SimpleNamespace(
        not_durable=lambda: lost["n"], saves=SimpleNamespace(error="ENOSPC No space left on device")))
    assert _final_checkpoint_failed(loop) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("khgrl learner: error: the final checkpoint in /data/ck failed "
                                               "(ENOSPC No space left on device): the 60 transitions received")
    assert "re-send it to a learner restarted with --resume" in err[0]
    lost["n"] = 0
    assert _final_checkpoint_failed(loop) == 1
    assert "the last checkpoint and the journal hold every transition received" in capsys.readouterr().err
