"""``khgrl stop`` / ``khgrl ready`` (deploy/run/stop.py): what confirms a command, and where the run is found."""

from __future__ import annotations

import pytest
from khgrl.deploy.run.stop import _confirmed, build_parser, main, target


def test_a_command_is_confirmed_by_the_actors_status_after_it_or_by_the_actor_gone():
    assert _confirmed("stop", False, None) and not _confirmed("stop", True, "")
    assert not _confirmed("estop", True, None) and not _confirmed("estop", True, "")  # no status yet, or not held
    assert _confirmed("estop", True, "e-stop by launcher") and _confirmed("estop", False, None)
    assert not _confirmed("release", True, "e-stop by launcher") and _confirmed("release", True, "")
    assert not _confirmed("ready", True, "waiting for ready before episode 3 (...)")
    assert _confirmed("ready", True, "") and _confirmed("ready", True, "paused by the launcher")


def test_the_run_is_found_in_its_directory_and_a_secure_one_uses_the_launchers_certificate(tmp_path):
    from khgrl.common.config.settings import resolve, write_run_config

    cfg = resolve(overrides={"run_dir": str(tmp_path)})
    write_run_config(tmp_path, cfg, {"run": "r1", "endpoint": "tls/127.0.0.1:7447", "secure": True})
    conf = tmp_path / "certs" / "zenoh" / "launcher.json5"
    conf.parent.mkdir(parents=True)
    conf.write_text("{}")
    assert target(build_parser().parse_args([str(tmp_path), "--now"])) == ("r1", "tls/127.0.0.1:7447", str(conf))
    assert target(build_parser("khgrl ready").parse_args(["--run", "r", "--connect", "tcp/h:1"])) == \
        ("r", "tcp/h:1", None)
    with pytest.raises(ValueError, match="RUN_DIR"):
        target(build_parser().parse_args([]))
    with pytest.raises(SystemExit):
        build_parser("khgrl ready").parse_args(["--now"])  # ready has no --now


def test_a_missing_run_directory_is_one_line_and_exit_2(tmp_path, capsys):
    assert main([str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not exist" in err


def test_a_run_that_has_ended_is_said_so_rather_than_blaming_the_router(tmp_path, capsys):
    """A tired user's ``khgrl stop RUN_DIR --now`` after the run ended: before this test the line was "no Zenoh
    router reachable at ..." after 5 s (true, but the router is gone because the run is over). Now: the run has
    ended, as summary.json says, and the e-stop state is still written for a --resume (one line, exit 1, at once)."""
    import json
    import socket

    from khgrl.common.config.settings import resolve, write_run_config

    with socket.socket() as s:  # a port nobody listens on: the run's router is gone
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = resolve(overrides={"run_dir": str(tmp_path)})
    write_run_config(tmp_path, cfg, {"run": "r1", "endpoint": f"tcp/127.0.0.1:{port}"})
    (tmp_path / "summary.json").write_text(json.dumps({"run": "r1", "ended": "finished", "wall_time_s": 42.0}))
    assert main([str(tmp_path), "--now"]) == 1
    err = capsys.readouterr().err
    assert "run r1 has ended (finished after 42 s" in err and "router" not in err, err
    assert "estop.json" in err and (tmp_path / "estop.json").is_file()
