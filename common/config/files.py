"""Settings files: the one reader of TOML/JSON settings (run configurations, experiment grids) and the writer of a
run's ``config.toml`` / ``config.json`` (:mod:`khgrl.common.config.settings` builds and checks the settings)."""

from __future__ import annotations

import json
import tomllib
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

__all__ = ["read_table", "load_file", "to_toml", "write_run_config"]


def read_table(path: str | Path) -> dict:
    """A settings file as a table: TOML (``.toml``) or JSON (``.json``); errors name the file. The one reader of
    settings files (run configs here, experiment grids in :mod:`khgrl.deploy.experiments.experiment`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {path} does not exist")
    try:
        data = json.loads(path.read_text()) if path.suffix == ".json" else tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'TOML'}: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a table of settings")
    return data


def load_file(path: str | Path) -> dict:
    """A run config file (:func:`read_table`; ``runtime`` of a run's config.json is kept apart, see read_run_file)."""
    data = read_table(path)
    data.pop("runtime", None)
    return data


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def to_toml(cfg: Any) -> str:
    """The configuration as TOML, each setting with its help as a comment (reads back to the same config)."""
    lines = ["# KhGRL run configuration (khgrl up --config FILE); every flag of khgrl up overrides it.", ""]

    def table(obj, name: str | None) -> None:
        if name:
            lines.extend(["", f"[{name}]"])
        for f in fields(obj):
            v = getattr(obj, f.name)
            if is_dataclass(v):
                continue
            lines.append(f"# {f.metadata['help']}")
            lines.append(f"{f.name} = {_toml_value(v)}")

    table(cfg, None)
    for f in fields(cfg):
        if is_dataclass(getattr(cfg, f.name)):
            table(getattr(cfg, f.name), f.name)
    return "\n".join(lines) + "\n"


def write_run_config(run_dir: str | Path, cfg: Any, runtime: dict) -> Path:
    """``RUN_DIR/config.toml`` (the resolved settings) and ``RUN_DIR/config.json`` (the same plus ``runtime``:
    run id, endpoint, actor ids, command line, start time) -- the file every child process reads."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.toml").write_text(to_toml(cfg))
    path = run_dir / "config.json"
    path.write_text(json.dumps({**cfg.to_dict(), "runtime": runtime}, indent=2))
    return path
