"""Per-episode statistics of a passage-world run: what the progress view, CSV/JSON and TensorBoard show."""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["EpisodeStats", "EpisodeAccumulator", "write_episodes", "append_episode_row", "append_row"]


@dataclass
class EpisodeStats:
    episode: int  # 1-based
    steps: int = 0
    ret: float = 0.0
    success: bool = False
    failure: bool = False  # blocked too long
    action_cost: float = 0.0  # sum of r_a
    obstacle_cost: float = 0.0  # sum of r_o (<= 0)
    passage_cost: float = 0.0  # sum of r_p (<= 0)
    obstacle_steps: int = 0
    interventions: int = 0  # number of press..release segments
    intervention_steps: int = 0
    clipped_steps: int = 0  # human actions clipped to [-1, 1]
    projected_steps: int = 0  # corrections projected onto the workspace
    mean_abs_xi_h: float = 0.0
    scale_max: list = field(default_factory=list)  # max over the episode of L per dimension
    wall_time: float = 0.0
    violation_steps: int = 0  # steps whose commanded P_t violated a hard constraint G P >= c
    workspace_exits: int = 0  # steps whose policy asked for a position outside the workspace box
    human_seconds: float = 0.0  # wall seconds of the intervened steps (from the previous step's end)
    rate_limited_steps: int = 0  # steps whose position sent was limited in speed or acceleration (--rate-limit)

    def to_row(self) -> dict:
        row = asdict(self)
        row["scale_max"] = ";".join(f"{v:.4g}" for v in self.scale_max)
        return row


class EpisodeAccumulator:
    """Feed it every step's (reward, info); it closes an :class:`EpisodeStats` at episode end."""

    def __init__(self) -> None:
        self.episode = 0
        self._open: EpisodeStats | None = None
        self._in_iv = False
        self._xi_sum = 0.0
        self._last = time.perf_counter()

    def start(self) -> None:
        self.episode += 1
        self._open = EpisodeStats(episode=self.episode)
        self._in_iv = False
        self._xi_sum = 0.0
        self._last = time.perf_counter()

    def add(self, reward: float, info: dict) -> None:
        if self._open is None:
            self.start()
        st = self._open
        st.steps += 1
        st.ret += float(reward)
        st.action_cost += float(info.get("r_a", 0.0))
        st.obstacle_cost += float(info.get("r_o", 0.0))
        st.passage_cost += float(info.get("r_p", 0.0))
        st.obstacle_steps += int(bool(info.get("in_obstacle", False)))
        st.violation_steps += int(bool(info.get("violation", False)))
        st.workspace_exits += int(bool(info.get("workspace_exit", False)))
        st.rate_limited_steps += int(bool(info.get("rate_limited", False)))
        now = time.perf_counter()
        iv = bool(info.get("intervened", False))
        if iv:
            st.human_seconds += now - self._last
            st.intervention_steps += 1
            st.clipped_steps += int(bool(info.get("clipped", False)))
            st.projected_steps += int(bool(info.get("projected", False)))
            self._xi_sum += float(np.mean(np.abs(info["xi_h"]))) if "xi_h" in info else 0.0
            if not self._in_iv:
                st.interventions += 1
        self._in_iv = iv
        self._last = now
        if "scale" in info:
            sc = np.asarray(info["scale"], dtype=np.float64)
            st.scale_max = sc.tolist() if not st.scale_max else np.maximum(st.scale_max, sc).tolist()
        st.success = st.success or bool(info.get("success", False))
        st.failure = st.failure or bool(info.get("failure", False))

    def finish(self, wall_time: float = 0.0) -> EpisodeStats:
        st = self._open if self._open is not None else EpisodeStats(episode=self.episode)
        st.mean_abs_xi_h = self._xi_sum / st.intervention_steps if st.intervention_steps else 0.0
        st.wall_time = wall_time
        self._open = None
        return st


def append_episode_row(path: str | Path, st: EpisodeStats) -> None:
    """Append one episode to an ``episodes.csv`` (the header first if the file is new or empty).

    :param path: the CSV file.
    :param st: the finished episode.
    """
    append_row(path, st.to_row())


def append_row(path: str | Path, row: dict) -> None:
    """Append one row to a CSV file (the header, the row's keys, first if the file is new or empty).

    :param path: the CSV file.
    :param row: column -> value.
    """
    path = Path(path)
    header = not path.is_file() or path.stat().st_size == 0
    with open(path, "a", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(row.keys()))
        if header:
            writer.writeheader()
        writer.writerow(row)


def write_episodes(run_dir: str | Path, episodes: list[EpisodeStats], config: dict) -> None:
    """episodes.csv + episodes.json + config.json in ``run_dir``."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(config, indent=2, default=str))
    rows = [e.to_row() for e in episodes]
    (run_dir / "episodes.json").write_text(json.dumps([asdict(e) for e in episodes], indent=2))
    if rows:
        with open(run_dir / "episodes.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
            writer.writeheader()
            writer.writerows(rows)
