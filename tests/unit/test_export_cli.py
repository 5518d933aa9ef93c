"""``khgrl export``: its help states the defaults; what cannot be exported is one line, exit 2, nothing written."""

from __future__ import annotations

from pathlib import Path

from khgrl.deploy.cli import build_parser, main


def test_help_states_defaults(capsys) -> None:
    help_text = " ".join(build_parser()._subparsers._group_actions[0].choices["export"].format_help().split())
    assert "(default: the run's --rate if > 0, else 10)" in help_text
    assert "(default: refuse it)" in help_text and "complementary_info.is_intervention" in help_text


def test_bad_run_dirs_are_refused(tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    assert main(["export", str(tmp_path / "missing"), "--lerobot", str(out)]) == 2
    assert "no such run directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["export", str(tmp_path / "empty"), "--lerobot", str(out)]) == 2
    assert "no config.json" in capsys.readouterr().err
    (tmp_path / "empty" / "config.json").write_text("{}")
    assert main(["export", str(tmp_path / "empty"), "--lerobot", str(out)]) == 2
    assert "no step records" in capsys.readouterr().err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["empty"]
