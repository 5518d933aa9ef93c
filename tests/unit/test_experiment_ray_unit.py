"""khgrl experiment --ray without a cluster: a run folder's pack and atomic unpack (nothing overwritten, nothing
half left), the Ray settings' validation, the worker's version check, and what the head does with a finished, a
failed and a refused run."""

from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path
from types import SimpleNamespace

import pytest
from khgrl.deploy.experiments.experiment import ExperimentConfig, load_config
from khgrl.deploy.experiments.experiment_progress import Progress, last_line
from khgrl.deploy.experiments.experiment_ray import RayRunner, unpack_run
from khgrl.deploy.experiments.ray_worker import check_identity, khgrl_identity, pack_run


def _run_folder(root: Path) -> Path:
    run = root / "src" / "low_cov-kgrl-seed0"
    (run / "actor-a0").mkdir(parents=True)
    (run / "actor-a0" / "episodes.csv").write_text("episode,ret\n1,-3.5\n")
    (run / "summary.json").write_text(json.dumps({"failed": []}))
    return run


def _unpacking_leftovers(parent: Path) -> list[str]:
    return [p.name for p in parent.iterdir() if p.name.endswith(".unpacking")]


def test_pack_then_unpack_gives_the_same_folder(tmp_path):
    data = pack_run(_run_folder(tmp_path))
    dest = tmp_path / "out" / "low_cov-kgrl-seed0"
    assert unpack_run(data, dest)
    assert (dest / "actor-a0" / "episodes.csv").read_text() == "episode,ret\n1,-3.5\n"
    assert json.loads((dest / "summary.json").read_text()) == {"failed": []}
    assert _unpacking_leftovers(dest.parent) == []


def test_unpack_never_overwrites_and_leaves_nothing_when_refused_or_broken(tmp_path):
    data = pack_run(_run_folder(tmp_path))
    out = tmp_path / "out"
    dest = out / "run"
    dest.mkdir(parents=True)
    (dest / "mine.txt").write_text("keep")
    with pytest.raises(FileExistsError):
        unpack_run(data, dest)
    assert [p.name for p in dest.iterdir()] == ["mine.txt"]
    other = out / "other"
    assert not unpack_run(data, other, accept=lambda d: (d / "summary.json").exists() and False)
    assert not other.exists() and _unpacking_leftovers(out) == []
    with pytest.raises(ValueError, match="broken"):
        unpack_run(data[: len(data) // 2], other)  # cut short in transit
    assert not other.exists() and _unpacking_leftovers(out) == []


def test_unpack_refuses_paths_outside_the_run(tmp_path):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        info = tarfile.TarInfo("../escaped.txt")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(ValueError, match="unsafe"):
        unpack_run(buf.getvalue(), tmp_path / "out" / "run")
    assert not (tmp_path / "out" / "escaped.txt").exists() and not (tmp_path / "out" / "run").exists()


@pytest.mark.parametrize("text,match", [
    ('ray = 5', "address string"),
    ('ray = "auto"\nray_cpus = 0', "ray_cpus must be > 0"),
    ('ray = "auto"\nray_gpus = -1', "ray_gpus >= 0"),
    ('ray = "auto"\nray_cpus = "two"', "ray_cpus must be a number"),
    ('ray = "auto"\nray_gpus = true', "ray_gpus must be a number"),
    ('ray = "auto"\nray_gpus = 1\nsystem = "reference"\nmethods = ["kgrl"]', "distributed"),
])
def test_bad_ray_settings_are_refused(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text + "\n")
    with pytest.raises(ValueError, match=match):
        load_config(f, {})


def test_ray_settings_from_the_file_and_the_command_line(tmp_path):
    f = tmp_path / "exp.toml"
    f.write_text('ray = "10.0.0.1:6379"\nray_gpus = 0.5\n')
    cfg = load_config(f, {"ray_cpus": 3, "ray": None})
    assert (cfg.ray, cfg.ray_cpus, cfg.ray_gpus) == ("10.0.0.1:6379", 3, 0.5)
    assert (ExperimentConfig().ray, ExperimentConfig().ray_cpus, ExperimentConfig().ray_gpus) == ("", 2.0, 0.0)


def test_the_worker_refuses_another_khgrl():
    mine = khgrl_identity()
    check_identity(mine)  # the same: fine
    with pytest.raises(RuntimeError, match="install the head's khgrl"):
        check_identity({**mine, "version": "0.0.0-other"})
    if mine["commit"]:
        with pytest.raises(RuntimeError, match="install the head's khgrl"):
            check_identity({**mine, "commit": "0" * 40})


class _Recorder:
    """The parts of the experiment's runner that RayRunner uses."""

    def __init__(self, out: Path) -> None:
        self.cfg = ExperimentConfig(out=str(out), ray="auto", episodes=1)
        self.out, self.stopping, self.records = out, False, {}
        self.finished: dict[str, tuple] = {}
        self.progress = SimpleNamespace(start=lambda *a, **k: None, advance=lambda *a: None,
                                        finish=lambda name, *a: self.finished.update({name: a}),
                                        skip=lambda *a: None)

    def record(self, name: str, **info) -> None:
        self.records[name] = {**self.records.get(name, {}), **info}


def test_the_head_keeps_a_finished_run_and_records_a_failed_one_without_a_folder(tmp_path):
    data = pack_run(_run_folder(tmp_path))
    out = tmp_path / "out"
    out.mkdir()
    runner = _Recorder(out)
    ray = RayRunner(runner, argv_of=lambda s: [], is_done=lambda d: (d / "summary.json").exists())
    end = {"event": "end", "node": "n1", "wall_time_s": 12.5, "tar": data, "log_tail": "last lines"}
    ray.live = {n: object() for n in ("good", "bad", "refused", "died", "broken")}
    ray._event("good", {"event": "start", "node": "n1"})
    ray._event("good", {**end, "returncode": 0})
    ray._event("bad", {**end, "returncode": 3})
    ray.is_done = lambda d: False
    ray._event("refused", {**end, "returncode": 0})  # exit 0 but not a finished run
    ray._event("broken", {**end, "returncode": 0, "tar": data[:100]})
    ray._failed("died", RuntimeError("worker died\nNo module named 'khgrl'"))
    assert ray.status == {"good": "done", "bad": "failed", "refused": "failed", "died": "failed",
                          "broken": "failed"}
    assert sorted(p.name for p in out.iterdir()) == ["good"] and ray.live == {}
    good, bad, died = runner.records["good"], runner.records["bad"], runner.records["died"]
    assert (good["status"], good["node"], good["wall_time_s"], good["returncode"]) == ("done", "n1", 12.5, 0)
    assert "log_tail" not in good and bad["log_tail"] == "last lines" and bad["returncode"] == 3
    assert "khgrl is not installed on the worker" in died["error"]
    assert "broken" in runner.records["broken"]["error"]
    # a failed run says why on the terminal, not only in experiment.json (issue 36: before, only the status)
    assert runner.finished["bad"][-1] == "last lines"
    assert "khgrl is not installed on the worker" in runner.finished["died"][-1]


def test_a_failed_run_prints_its_reason(capsys):
    progress = Progress(total_runs=2, episodes=1, enabled=False)
    progress.finish("r1", "failed", 3.0, last_line("starting\nkhgrl up: error: no module named 'mytask'\n\n"))
    progress.finish("r2", "done", 9.0, "ignored for a finished run")
    out = capsys.readouterr().out.splitlines()
    assert out == ["r1: failed in 3 s: khgrl up: error: no module named 'mytask'", "r2: done in 9 s"]


def test_after_ctrl_c_a_run_finished_before_counts_as_done_and_the_rest_as_not_started(tmp_path):
    from khgrl.deploy.experiments.experiment import RunSpec, _Runner

    cfg = ExperimentConfig(out=str(tmp_path), tasks=["fetch:moved"], methods=["khgrl"], seeds=[0, 1], episodes=3)
    finished = tmp_path / "fetch_moved-khgrl-seed0"
    finished.mkdir()
    (finished / "summary.json").write_text(json.dumps({"failed": [], "exit_codes": {"a0": 0},
                                                       "a0": {"episodes": 3, "unconfirmed_transitions": 0}}))
    runner = _Runner(cfg, [], Progress(total_runs=2, episodes=3, enabled=False))
    runner.stopping = True  # Ctrl-C before these runs' turn came (before: both "not started")
    assert [runner.one(RunSpec("fetch_moved", "khgrl", s, "fetch:moved")) for s in (0, 1)] == ["done", "not started"]
    assert json.loads((tmp_path / "experiment.json").read_text())["runs"] == {
        "fetch_moved-khgrl-seed0": {"status": "done", "reused": True}}
