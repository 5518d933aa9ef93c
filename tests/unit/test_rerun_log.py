"""The pure pieces of the Rerun view: the band, 3-D points, ``--view`` parsing and refusals, the children's target,
the logger into a file read back with Rerun's reader, and a live view that survives its own errors."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from khgrl.common.rerun_log import VIEW_ENV, RunLogger, ViewTarget, band_edges, band_half, open_recording, to3
from khgrl.deploy.run.view_sink import parse_view

rerun = pytest.importorskip("rerun", reason="the view needs rerun-sdk (pip install -e '.[test]' has it)")


def test_band_is_the_gui_band_mean_plus_minus_abs_projector_times_scale() -> None:
    from khgrl.human_bridge.gui.task import band

    rng = np.random.default_rng(0)
    h, o = 7, 3
    a = rng.normal(size=(h, o, o))
    proj = a @ a.transpose(0, 2, 1)  # symmetric, with negative off-diagonal entries
    mean, scale = rng.normal(size=(h, o)), rng.uniform(0.1, 5.0, size=(h, o))
    want = band(None, scale, mean, proj)  # (H, 2, O)
    low, high = band_edges({"t": np.arange(h), "mean": mean, "scale": scale, "kmp_projector": proj})
    np.testing.assert_allclose(low, want[:, 0])
    np.testing.assert_allclose(high, want[:, 1])
    np.testing.assert_allclose(band_half(proj[2], scale[2]), np.abs(proj[2]) @ scale[2])
    # steps past the grid use its last projector
    low2, _ = band_edges({"t": np.array([h + 5]), "mean": mean[-1:], "scale": scale[-1:], "kmp_projector": proj})
    np.testing.assert_allclose(low2, want[-1:, 0])


def test_points_are_three_dimensional() -> None:
    np.testing.assert_array_equal(to3([[1.0, 2.0]]), [[1.0, 2.0, 0.0]])  # a 2-D task at z = 0
    np.testing.assert_array_equal(to3([1.0, 2.0, 3.0, 4.0]), [1.0, 2.0, 3.0])
    assert to3(np.zeros((4, 5, 2))).shape == (4, 5, 3)


def test_view_spec_is_checked_and_an_existing_file_refused(tmp_path: Path) -> None:
    assert parse_view("none").kind == "none"
    assert parse_view("rerun:web").kind == "web"
    out = tmp_path / "run.rrd"
    spec = parse_view(f"rerun:{out}")
    assert spec.kind == "file" and spec.file == out.resolve()
    out.write_bytes(b"earlier")
    with pytest.raises(ValueError, match="--overwrite"):
        parse_view(f"rerun:{out}")
    assert parse_view(f"rerun:{out}", overwrite=True).file == out.resolve()
    assert out.read_bytes() == b"earlier"  # (replaced only when the run starts)
    inside = tmp_path / "run" / "sub" / "v.rrd"  # in the run directory: its folders are made when the run starts
    assert parse_view(f"rerun:{inside}", run_dir=tmp_path / "run").file == inside.resolve()
    for bad, why in (("rviz", "expected none"), (f"rerun:{tmp_path / 'x.txt'}", "must end in .rrd"),
                     (f"rerun:{tmp_path / 'no' / 'x.rrd'}", "no directory")):
        with pytest.raises(ValueError, match=why):
            parse_view(bad)


def test_native_viewer_needs_a_display(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ValueError, match="rerun:FILE.rrd"):
        parse_view("rerun")


def test_up_help_shows_the_view_flags_and_defaults() -> None:
    from khgrl.deploy.run.launcher import build_parser

    text = build_parser().format_help()
    assert "--view SPEC" in text and "(default: none)" in text and "--view-camera-every" in text
    args = build_parser().parse_args([])
    assert args.view == "none" and args.view_camera_every == 10


def test_view_target_travels_in_the_environment() -> None:
    t = ViewTarget("rerun+http://127.0.0.1:9/proxy", camera_every=5, camera_size=64)
    assert ViewTarget.from_env({VIEW_ENV: t.to_env()}) == t
    assert ViewTarget.from_env({}) is None
    with pytest.raises(ValueError, match=VIEW_ENV):
        ViewTarget.from_env({VIEW_ENV: "{not json"})


def test_view_command_refuses_an_existing_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from khgrl.deploy.tools.view_cmd import main

    run = tmp_path / "run"
    (run / "actor-a0" / "steps").mkdir(parents=True)
    (run / "actor-a0" / "steps" / "episode-000001.npz").write_bytes(b"")
    out = tmp_path / "old.rrd"
    out.write_bytes(b"keep")
    assert main([str(run), "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err and out.read_bytes() == b"keep"
    assert main([str(tmp_path / "none"), "--out", str(tmp_path / "a.rrd")]) == 2
    assert main([str(tmp_path), "--out", str(tmp_path / "a.rrd")]) == 2  # no step records
    assert "no step records" in capsys.readouterr().err


def _row(t: int, intervened: bool) -> dict:
    return {"t": t, "robot": np.array([0.1 * t, 0.2]), "desired": np.array([0.1 * t, 0.3]),
            "mean": np.array([0.1 * t, 0.25]), "scale": np.array([2.0, 3.0]),
            "p_h": np.array([0.5, 0.5 + t]) if intervened else np.full(2, np.nan), "intervened": intervened}


def test_logger_writes_what_the_reader_gets_back(tmp_path: Path) -> None:
    from rrd_read import by_episode, by_step, read_rrd

    path = tmp_path / "unit.rrd"
    rec = open_recording("unit-run", save=str(path))
    log = RunLogger(rec, "a7")
    log.scene(np.zeros((2, 5, 2)), ([0.0, 0.0], [1.0, 1.0]))
    proj = np.stack([np.eye(2)] * 4)
    log.start(3, {"kmp_mean": np.zeros((4, 2)), "kmp_projector": proj, "via": np.zeros((0, 3))})
    rows = [_row(t, t in (1, 2)) for t in range(4)]
    for r in rows:
        log.step(3, r, proj[r["t"]])
    arrays = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    log.finish(3, {**arrays, "kmp_projector": proj}, ret=-1.5, success=True)
    rec.flush()
    rec.disconnect()
    recordings, got = read_rrd(path)
    assert [r.recording_id for r in recordings] == ["unit-run"]
    robot = by_step(got["/actor/a7/robot"], "Points3D:positions")
    assert sorted(robot) == [(3, t) for t in range(4)]
    np.testing.assert_allclose(robot[(3, 2)], [0.2, 0.2, 0.0], rtol=1e-6)
    assert sorted(by_step(got["/actor/a7/p_h"], "Points3D:positions")) == [(3, 1), (3, 2)]  # cleared at step 3
    assert by_episode(got["/actor/a7/episode/return"]) == {3: -1.5}
    box = got["/actor/a7/band/now"][0]
    np.testing.assert_allclose(box["Boxes3D:half_sizes"][0], [2.0, 3.0, 0.0])


def test_live_view_survives_its_own_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import khgrl.actor.viewer as viewer

    monkeypatch.setattr(viewer, "open_recording", lambda run, url: open_recording(run, save=str(tmp_path / "l.rrd")))

    def broken_camera(size: int) -> np.ndarray:
        raise RuntimeError("no OpenGL here")

    world = SimpleNamespace(demos=np.zeros((1, 3, 2)), low=np.zeros(2), high=np.ones(2),
                            view=SimpleNamespace(shapes=()))
    env = SimpleNamespace(world=world, inner=SimpleNamespace(camera_frame=broken_camera))
    view = viewer.LiveView(ViewTarget("unused", camera_every=1), "r", "a0", env, version=lambda: 4)
    proj = np.stack([np.eye(2)] * 3)
    view.start(1, {"kmp_mean": np.zeros((3, 2)), "kmp_projector": proj, "via": np.zeros((0, 3))})
    view.step(1, _row(0, False))
    assert view.camera is None and view.on  # the camera alone is off
    view.step(1, {"t": 1})  # a row the logger cannot log: the view turns off, the caller goes on
    assert not view.on
    view.step(1, _row(2, False))
    view.finish(1, {}, SimpleNamespace(ret=0.0, success=False))
    view.close()


def test_the_web_viewer_ends_with_the_run(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``--view rerun:web``: Rerun's real web-viewer sink starts and serves, and is stopped when the run's view
    closes. Before (issue 36): it stayed after the run ("kill PID"), a server left behind."""
    from khgrl.deploy.run.view_sink import RunView

    view = RunView(parse_view("rerun:web"), run_id="r", log_dir=tmp_path)
    with view:
        sink = view.sink
        assert sink is not None and sink.poll() is None
    assert sink.poll() is not None
    assert "until the run ends" in capsys.readouterr().out
