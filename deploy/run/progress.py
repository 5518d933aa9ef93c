"""What ``khgrl up`` shows while a run goes on: a live table (rich) of each actor's episodes, successes, last
return and human interventions, with the learner's ingest, gradient steps and weights version as its caption
(and, in red, a failing checkpoint: a full or unwritable disk); or, with ``--no-progress``, one plain line per
finished episode (``[a0] episode 3: return ...``, the line ``khgrl experiment`` follows) and one when the
learner's checkpoints start failing or recover.

The live table needs a terminal. When stdout is not one (``khgrl up ... > log``, a pipe, CI) the view prints the
plain lines as episodes end and, at the end, the same table once in plain text, as wide as its cells (nothing cut),
every line ended.

It gets typed, already validated messages (:class:`khgrl.common.wire.messages.EpisodeReport`,
:class:`khgrl.common.wire.messages.Status` with :class:`khgrl.common.wire.messages.LearnerInfo`) and only formats them.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from khgrl.common.wire.messages import ActorInfo, EpisodeReport, LearnerInfo, Status

__all__ = ["ProgressView", "ActorRow", "episode_line", "checkpoint_line", "plain_table"]

_COLUMNS = ("actor", "episodes", "successes", "last return", "interventions", "human steps", "clipped", "mean |xi_h|")
_WIDTHS = (5, 9, 9, 7, 13, 6, 9, 6)  # the live table's columns: 64 characters, 2 between them: 78


def _stat(stats: dict, name: str) -> float:
    """A numeric episode statistic (EpisodeReport checked its type; absent counts as 0)."""
    value = stats.get(name)
    return 0.0 if value is None else float(value)


def episode_line(report: EpisodeReport) -> str:
    """The plain one-line summary of a finished episode."""
    st = report.stats
    steps, clipped = int(_stat(st, "intervention_steps")), int(_stat(st, "clipped_steps"))
    frac = f"{clipped / steps:.0%}" if steps else "-"
    return (f"[{report.actor}] episode {st['episode']}: return {_stat(st, 'ret'):.1f} success={st.get('success')} "
            f"interventions={steps} (count {int(_stat(st, 'interventions'))}, clipped {frac}, "
            f"mean |xi_h| {_stat(st, 'mean_abs_xi_h'):.3g})")


def checkpoint_line(info: LearnerInfo, markup: bool = False) -> str:
    """What the learner's status says of its checkpoints when they fail (empty when they do not).

    :param info: the learner's status
    :param markup: rich markup (red, the reason escaped) for the live table
    """
    if not info.checkpoint_error:
        return ""
    reason = info.checkpoint_error[:200]
    head = "CHECKPOINT FAILING"
    if markup:
        from rich.markup import escape

        head, reason = f"[bold red]{head}[/]", escape(reason)
    return (f"{head} ({info.checkpoint_failures} failed saves): {reason} -- training goes on, the actors keep "
            "what is not saved, retried with backoff")


def plain_table(title: str, header: tuple[str, ...] | list[str], rows: list[list[str]], caption: str = "") -> str:
    """A table as plain text: right-aligned columns as wide as their widest cell (headers never cut), the title
    above, the caption below, every line ended with a newline.

    :param title: the line above the table
    :param header: the column names
    :param rows: the cells, one list per row
    :param caption: lines below the table (may hold newlines)
    """
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    line = lambda cells: "  ".join(str(c).rjust(w) for c, w in zip(cells, widths)).rstrip()  # noqa: E731
    out = [title, line(header), "  ".join("-" * w for w in widths), *(line(r) for r in rows)]
    out += caption.splitlines() if caption else []
    return "\n".join(out) + "\n"


@dataclass
class ActorRow:
    """One actor's totals over the episodes reported so far."""

    done: int = 0
    success: int = 0
    last_return: float | None = None
    count: int = 0  # interventions
    steps: int = 0  # human steps
    clipped: int = 0
    xi_sum: float = 0.0  # sum of mean |xi_h| weighted by human steps

    def add(self, stats: dict) -> None:
        steps = int(_stat(stats, "intervention_steps"))
        self.done = max(self.done, int(stats["episode"]))
        self.success += int(stats.get("success") is True)
        self.last_return = _stat(stats, "ret")
        self.count += int(_stat(stats, "interventions"))
        self.steps += steps
        self.clipped += int(_stat(stats, "clipped_steps"))
        self.xi_sum += _stat(stats, "mean_abs_xi_h") * steps

    def cells(self, name: str, episodes: int) -> list[str]:
        n = self.steps
        ret = "-" if self.last_return is None else f"{self.last_return:.1f}"
        clipped = f"{self.clipped} ({self.clipped / n:.0%})" if n else str(self.clipped)
        xi = f"{self.xi_sum / n:.3g}" if n else "-"
        return [name, f"{self.done}/{episodes}", str(self.success), ret, str(self.count), str(n), clipped, xi]


SCHEDULE_HOLD = "waiting for the learner"  # simulation mode's lock-step wait (the watchdog's reason starts so)


class ProgressView:
    """The live table (``enabled`` on a terminal) or plain episode lines; use it as a context manager.

    :param actors: the run's actor ids (rows in this order; other actors get a row when they report)
    :param episodes: episodes per actor in the whole run
    :param enabled: the table was asked for (``--progress``): live on a terminal; elsewhere plain episode lines
        and the table once, in plain text, at the end. False (``--no-progress``): the lines only.
    :param tty: whether stdout is a terminal (None: ask ``sys.stdout``)
    :param schedule_quiet: simulation mode: the lock-step waits for the learner are the schedule, not news -- no
        "robot held: waiting for the learner" / "robot released" line for them (robot mode: every hold is said)
    """

    def __init__(self, actors: list[str], episodes: int, enabled: bool, tty: bool | None = None,
                 schedule_quiet: bool = False) -> None:
        self.rows = {a: ActorRow() for a in actors}
        self.episodes = episodes
        self.enabled = enabled
        if tty is None:
            tty = bool(getattr(sys.stdout, "isatty", lambda: False)())
        self.live = enabled and tty
        self.learner: LearnerInfo | None = None
        self.held: dict[str, str] = {}  # actor -> why its robot is held ("": it is not)
        self.schedule_quiet = schedule_quiet
        self._said: dict[str, bool] = {}  # actor -> its last line said "robot held" (a release is said after one)
        self._live = None

    def __enter__(self) -> "ProgressView":
        if self.live:
            from rich.live import Live

            self._live = Live(self._table(), refresh_per_second=4, transient=False)
            self._live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._live is not None:
            self._live.update(self._table())
            self._live.__exit__(*exc)
            self._live = None
        elif self.enabled:
            print(self.final_text(), end="", flush=True)

    def episode(self, report: EpisodeReport) -> None:
        """A finished episode of one actor.

        :param report: the actor's decoded episode message
        """
        self.rows.setdefault(report.actor, ActorRow()).add(report.stats)
        if not self.live:
            print(episode_line(report), flush=True)
        self.refresh()

    def status(self, status: Status) -> None:
        """A process's status; the learner's goes into the caption.

        :param status: a decoded status message (info typed by role)
        """
        if isinstance(status.info, ActorInfo) and status.info.held != self.held.get(status.info.id, ""):
            self._held_line(status.info.id, status.info.held)
            self.refresh()
        if isinstance(status.info, LearnerInfo):
            before = self.learner.checkpoint_error if self.learner is not None else ""
            self.learner = status.info
            if not self.live and status.info.checkpoint_error != before:
                line = checkpoint_line(status.info) or f"checkpoint recovered ({status.info.checkpoints} saved)"
                print(f"[{status.info.id}] {line}", flush=True)
            self.refresh()

    def _held_line(self, actor: str, held: str) -> None:
        """The watchdog holds (or releases) ``actor``'s robot: say so, unless it is the schedule (see the class)."""
        self.held[actor] = held
        schedule = self.schedule_quiet and held.startswith(SCHEDULE_HOLD)
        said = self._said.get(actor, False)
        if self.live or schedule or (not held and not said):
            return
        print(f"[{actor}] " + (f"robot held: {held}" if held else "robot released"), flush=True)
        self._said[actor] = bool(held)

    def refresh(self) -> None:
        if self._live is not None:
            self._live.update(self._table())

    def caption(self, markup: bool = False, final: bool = False) -> str:
        """The learner's line (and a failing checkpoint's).

        :param markup: rich markup (the live table's)
        :param final: the run is over: no current rate (the learner's last status says 0/s once it stopped)
        """
        li = self.learner
        if li is None:
            return "learner: waiting"
        rate = "" if final else f" ({li.grad_steps_per_s:.0f}/s)"
        text = f"learner: {li.ingested} transitions, {li.gradient_steps} gradient steps{rate}, weights v{li.version}"
        if li.prior_fraction > 0:  # RLPD sampling (--sampling rlpd): the prior data and its achieved share
            sampled = li.sampled_prior + li.sampled_online
            share = f"{li.sampled_prior / sampled:.0%}" if sampled else "-"
            text += f", UTD {li.utd:.2f}, prior: {li.prior_slots} slots, {share} of samples"
        failing = checkpoint_line(li, markup=markup)
        held = "; ".join(f"{a}: {why}" for a, why in self.held.items() if why)
        text += f"\nrobot held -- {held}" if held else ""
        return f"{text}\n{failing}" if failing else text

    def final_text(self) -> str:
        """The table in plain text (stdout not a terminal): every header and cell whole, lines ended."""
        rows = [row.cells(name, self.episodes) for name, row in self.rows.items()]
        return plain_table("KhGRL run", _COLUMNS, rows, self.caption(final=True))

    def _table(self):
        from rich.table import Table

        # fixed widths, no rules: the table fits 80 columns with every header word whole (two-word
        # headers on two lines; a long cell folds instead of being cut)
        table = Table(title="KhGRL run", box=None, pad_edge=False)
        for col, width in zip(_COLUMNS, _WIDTHS):
            table.add_column(col, justify="right", width=width, overflow="fold")
        for name, row in self.rows.items():
            table.add_row(*row.cells(name, self.episodes))
        table.caption = self.caption(markup=True)
        return table
