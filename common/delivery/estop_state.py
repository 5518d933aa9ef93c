"""The run's e-stop state on disk (README, "On a real robot"): ``RUN_DIR/estop.json``, written by ``khgrl stop
--now`` / ``--release`` and by the run's supervisor (``khgrl up``, ``khgrl supervise``) when it hears a press or a
release, read by an actor before its first command. A restarted actor (or one started after the press) holds; a
file it cannot read counts as pressed. Lean (no numpy, no Zenoh): ``khgrl stop --now`` writes it first.

    {"pressed": true, "by": "launcher", "time": 1733333333.2}
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

__all__ = ["STATE_FILE", "EStopState", "read_state", "write_state"]

STATE_FILE = "estop.json"


class EStopState(dict):
    """What ``estop.json`` says: ``pressed`` (bool), ``by`` (who), ``time`` (when, ``time.time()``)."""

    @property
    def pressed(self) -> bool:
        return bool(self.get("pressed"))


def read_state(run_dir: str | Path) -> EStopState | None:
    """The run's e-stop state (None: no file, the e-stop was never pressed in this run directory); a file that cannot
    be read or parsed counts as pressed (``by`` says why).

    :param run_dir: the run directory.
    """
    path = Path(run_dir) / STATE_FILE
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        return EStopState(pressed=True, by=f"{path} cannot be read ({type(exc).__name__}: {exc})", time=time.time())
    if not isinstance(data, dict) or not isinstance(data.get("pressed"), bool):
        return EStopState(pressed=True, by=f"{path} is not an e-stop state", time=time.time())
    return EStopState(data)


def write_state(run_dir: str | Path, pressed: bool, by: str) -> Path:
    """Write the run's e-stop state (atomically: a reader sees the old state or the new one); raises OSError.

    :param run_dir: the run directory (must exist).
    :param pressed: pressed (True) or released.
    :param by: who pressed or released it.
    """
    path = Path(run_dir) / STATE_FILE
    tmp = path.with_name(f".{STATE_FILE}.{os.getpid()}")
    tmp.write_text(json.dumps({"pressed": bool(pressed), "by": by, "time": time.time()}))
    os.replace(tmp, path)
    return path
