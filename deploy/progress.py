"""What ``khgrl up`` shows while a run goes on: a live table (rich) of each actor's episodes, successes, last
return and human interventions, with the learner's ingest, gradient steps and weights version as its caption
(and, in red, a failing checkpoint: a full or unwritable disk); or, with ``--no-progress``, one plain line per
finished episode (``[a0] episode 3: return ...``, the line ``khgrl experiment`` follows) and one when the
learner's checkpoints start failing or recover.

It gets typed, already validated messages (:class:`khgrl.common.wire.messages.EpisodeReport`,
:class:`khgrl.common.wire.messages.Status` with :class:`khgrl.common.wire.messages.LearnerInfo`) and only formats them.
"""

from __future__ import annotations

from dataclasses import dataclass

from khgrl.common.wire.messages import EpisodeReport, LearnerInfo, Status

__all__ = ["ProgressView", "ActorRow", "episode_line", "checkpoint_line"]

_COLUMNS = ("actor", "episodes", "successes", "last return", "interventions", "human steps", "clipped", "mean |xi_h|")


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


class ProgressView:
    """The live table (``enabled``) or plain episode lines; use it as a context manager.

    :param actors: the run's actor ids (rows in this order; other actors get a row when they report)
    :param episodes: episodes per actor in the whole run
    :param enabled: live table if true, else one printed line per episode
    """

    def __init__(self, actors: list[str], episodes: int, enabled: bool) -> None:
        self.rows = {a: ActorRow() for a in actors}
        self.episodes = episodes
        self.enabled = enabled
        self.learner: LearnerInfo | None = None
        self._live = None

    def __enter__(self) -> "ProgressView":
        if self.enabled:
            from rich.live import Live

            self._live = Live(self._table(), refresh_per_second=4, transient=False)
            self._live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._live is not None:
            self._live.update(self._table())
            self._live.__exit__(*exc)
            self._live = None

    def episode(self, report: EpisodeReport) -> None:
        """A finished episode of one actor.

        :param report: the actor's decoded episode message
        """
        self.rows.setdefault(report.actor, ActorRow()).add(report.stats)
        if not self.enabled:
            print(episode_line(report), flush=True)
        self.refresh()

    def status(self, status: Status) -> None:
        """A process's status; the learner's goes into the caption.

        :param status: a decoded status message (info typed by role)
        """
        if isinstance(status.info, LearnerInfo):
            before = self.learner.checkpoint_error if self.learner is not None else ""
            self.learner = status.info
            if not self.enabled and status.info.checkpoint_error != before:
                line = checkpoint_line(status.info) or f"checkpoint recovered ({status.info.checkpoints} saved)"
                print(f"[{status.info.id}] {line}", flush=True)
            self.refresh()

    def refresh(self) -> None:
        if self._live is not None:
            self._live.update(self._table())

    def caption(self) -> str:
        li = self.learner
        if li is None:
            return "learner: waiting"
        text = (f"learner: {li.ingested} transitions, {li.gradient_steps} gradient steps "
                f"({li.grad_steps_per_s:.0f}/s), weights v{li.version}")
        failing = checkpoint_line(li, markup=self.enabled)
        return f"{text}\n{failing}" if failing else text

    def _table(self):
        from rich.table import Table

        table = Table(title="KhGRL run")
        for col in _COLUMNS:
            table.add_column(col, justify="right")
        for name, row in self.rows.items():
            table.add_row(*row.cells(name, self.episodes))
        table.caption = self.caption()
        return table
