"""The actor's result files in RUN_DIR/actor-ID/: ``episodes.csv`` and ``episodes.json`` (a row per finished
episode, written as it finishes, so a killed actor keeps its history), ``config.json`` and ``summary.json``; for a
task whose scene changes every episode also ``scenes.csv`` (a row per episode: its reset seed, placement, via-points
and the checks of the adapted KMP, ``KGRLEnv.scene_row``).
The columns of ``episodes.csv`` (:class:`khgrl.common.metrics.EpisodeStats`) are documented in the README,
section "episodes.csv" (tests/unit/test_newcomer_fixes.py checks that every column is).

With ``--resume`` (or when it continues the stream of a killed process, :mod:`khgrl.common.delivery.restart`) the actor
continues an earlier part of the run: its episodes are read back, numbering continues after the last one, and
new rows are appended. Otherwise earlier files are replaced.
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import asdict
from pathlib import Path

from khgrl.actor.record import trim_partial_line
from khgrl.common.metrics import EpisodeStats, append_episode_row, append_row

__all__ = ["EpisodeLog"]

log = logging.getLogger("khgrl.actor")


def _typed(value: str):
    """A value read back from episodes.csv as the type it was written from."""
    if value in ("True", "False"):
        return value == "True"
    for conv in (int, float):
        try:
            return conv(value)
        except ValueError:
            pass
    return value


def _from_csv_row(row: dict) -> dict:
    out = {k: _typed(v) for k, v in row.items()}
    sm = row.get("scale_max", "")
    out["scale_max"] = [float(v) for v in sm.split(";")] if sm else []
    return out


class EpisodeLog:
    """The finished episodes of this actor, earlier parts of the run included.

    :param out_dir: RUN_DIR/actor-ID.
    :param resume: continue the episodes already recorded there (else start afresh).
    :param until: ``--until-success`` (rate, window): the run ends early once the last ``window`` autonomous episodes
        succeed at ``rate`` or more (rate 0: never; :meth:`converged`).
    """

    def __init__(self, out_dir: Path, resume: bool, until: tuple[float, int] = (0.0, 20)) -> None:
        self.dir = Path(out_dir)
        self.csv = self.dir / "episodes.csv"
        self.json = self.dir / "episodes.json"
        self.earlier: list[dict] = []
        if resume:
            trim_partial_line(self.csv)  # (an actor killed while appending a row)
            self.earlier = self._read_earlier()
        else:
            for p in (self.csv, self.json, self.dir / "scenes.csv"):
                p.unlink(missing_ok=True)
        self.new: list[EpisodeStats] = []
        self.until, self.reached = until, False  # (--until-success; reached: the run ended early)

    def _read_earlier(self) -> list[dict]:
        """episodes.json, or episodes.csv where it has more rows (a part killed between the two writes)."""
        from_json = json.loads(self.json.read_text()) if self.json.is_file() else []
        if not isinstance(from_json, list):
            raise ValueError(f"{self.json}: expected a list of episodes")
        rows = []
        if self.csv.is_file():
            with open(self.csv, newline="") as fh:
                rows = list(csv.DictReader(fh))
        return from_json if len(from_json) >= len(rows) else [_from_csv_row(r) for r in rows]

    @property
    def last_episode(self) -> int:
        """The number of the last episode of the earlier parts (0: none)."""
        return max((int(e["episode"]) for e in self.earlier), default=0)

    @property
    def last_episode_run(self) -> int:
        """The number of the last episode finished, this part's or an earlier one's (0: none)."""
        return self.new[-1].episode if self.new else self.last_episode

    @property
    def earlier_transitions(self) -> int:
        """Transitions (steps) the earlier parts took."""
        return sum(int(e["steps"]) for e in self.earlier)

    def autonomous_success(self, window: int) -> float | None:
        """The success rate over the last ``window`` autonomous episodes (no human step), earlier parts included;
        None while fewer than ``window`` have run (``--until-success``).

        :param window: how many autonomous episodes to look back over.
        """
        rows = [(bool(e["success"]), int(e["intervention_steps"])) for e in self.earlier]
        rows += [(bool(e.success), int(e.intervention_steps)) for e in self.new]
        autonomous = [success for success, human in rows if human == 0][-window:]
        return sum(autonomous) / window if len(autonomous) == window else None

    def converged(self) -> bool:
        """``--until-success``: whether the last ``window`` autonomous episodes succeed at ``rate`` (> 0) or more
        (``until``); then the run ends early, said once in the log and kept in ``reached``."""
        rate, window = self.until
        if rate > 0 and not self.reached and (self.autonomous_success(window) or 0.0) >= rate:
            self.reached = True
            log.info("%.0f %% of the last %d autonomous episodes succeeded (--until-success %.2f): the run ends after "
                     "episode %d", 100 * self.autonomous_success(window), window, rate, self.last_episode_run)
        return self.reached

    def add(self, st: EpisodeStats, scene: dict | None = None) -> None:
        """Record a finished episode (appended to episodes.csv; episodes.json rewritten).

        :param st: the episode's statistics.
        :param scene: the episode's scene (``KGRLEnv.scene_row()``) for ``scenes.csv``; None: a fixed scene.
        """
        self.new.append(st)
        append_episode_row(self.csv, st)
        if scene is not None:
            append_row(self.dir / "scenes.csv", {"episode": st.episode, **scene})
        tmp = self.json.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.earlier + [asdict(e) for e in self.new], indent=2))
        tmp.replace(self.json)

    def write_final(self, config: dict, summary: dict) -> None:
        """``config.json`` and ``summary.json``.

        :param config: the resolved run configuration plus this actor's runtime facts.
        :param summary: this part's summary.
        """
        (self.dir / "config.json").write_text(json.dumps(config, indent=2, default=str))
        if not self.json.is_file():  # no episode finished in this part
            self.json.write_text(json.dumps(self.earlier, indent=2))
        (self.dir / "summary.json").write_text(json.dumps(summary, indent=2))
