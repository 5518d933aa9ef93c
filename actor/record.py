"""``RUN_DIR/actor-ID/corrections.csv``: one row per step at which the actor applied a human correction.
``khgrl human replay`` feeds such a file into a new run."""

from __future__ import annotations

import csv
import time
from pathlib import Path

__all__ = ["CorrectionRecord", "trim_partial_line"]


def trim_partial_line(path: Path) -> int:
    """Cut a last line that a killed process left unfinished (no newline) off a CSV file that is appended to;
    returns the bytes cut.

    :param path: the file (nothing happens if it is missing or empty).
    """
    path = Path(path)
    if not path.is_file() or path.stat().st_size == 0:
        return 0
    data = path.read_bytes()
    if data.endswith(b"\n"):
        return 0
    keep = data.rfind(b"\n") + 1
    with open(path, "r+b") as fh:
        fh.truncate(keep)
    return len(data) - keep


class CorrectionRecord:
    """Rows of run, actor, episode, step t, wall time, client, P_h as received, and whether it was projected
    onto the workspace / its action clipped.

    :param path: the CSV file.
    :param run: run id.
    :param actor: actor id.
    :param append: continue an existing file (``--resume``: no second header); otherwise start it afresh.
    :param dim: O, the size of P_h (columns p_h_x, p_h_y, p_h_z, p_h_3, ...).
    """

    FIELDS = ("run", "actor", "episode", "step", "time", "client", "p_h_x", "p_h_y", "projected", "clipped", "source")

    def __init__(self, path: Path, run: str, actor: str, append: bool = False, dim: int = 2) -> None:
        self.path = Path(path)
        names = tuple(f"p_h_{'xyz'[k] if k < 3 else k}" for k in range(dim))
        self.FIELDS = ("run", "actor", "episode", "step", "time", "client", *names, "projected", "clipped", "source")
        self.run, self.actor = run, actor
        if append:
            trim_partial_line(self.path)  # a killed actor's last row may be half written
        has_rows = append and self.path.is_file() and self.path.stat().st_size > 0
        self._fh = open(self.path, "a" if has_rows else "w", newline="")
        self._w = csv.writer(self._fh)
        if not has_rows:
            self._w.writerow(self.FIELDS)
        self.rows = 0

    def write(self, episode: int, t: int, client: str | None, p_h, info: dict) -> None:
        """One applied correction.

        :param episode: the episode (whole run).
        :param t: the step.
        :param client: the client that held the robot.
        :param p_h: the P_h applied (as received).
        :param info: the environment's step info (``projected``, ``clipped``).
        """
        if self._fh.closed:
            return
        self._w.writerow((self.run, self.actor, int(episode), int(t), f"{time.time():.6f}", client or "",
                          *(repr(float(v)) for v in p_h), int(bool(info.get("projected"))),
                          int(bool(info.get("clipped"))), "physical" if client == "physical" else "remote"))
        self.rows += 1

    def flush(self) -> None:
        if not self._fh.closed:
            self._fh.flush()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()
