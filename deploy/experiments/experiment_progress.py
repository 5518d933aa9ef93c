"""``khgrl experiment``'s progress display: a bar per run and one for the grid, or plain lines without a
terminal; a failed run's reason on the terminal."""

from __future__ import annotations

__all__ = ["Progress", "last_line"]


class Progress:
    """One bar per run (episodes) and one overall bar (runs), or plain lines without a terminal."""

    def __init__(self, total_runs: int, episodes: int, enabled: bool) -> None:
        self.episodes, self.enabled = episodes, enabled
        self.tasks: dict[str, int] = {}
        self._p = None
        if enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._p = Progress(TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(),
                               TextColumn("{task.fields[note]}"), TimeElapsedColumn())
            self._overall = self._p.add_task("runs", total=total_runs, note="")

    def __enter__(self):
        if self._p is not None:
            self._p.start()
        return self

    def __exit__(self, *exc):
        if self._p is not None:
            self._p.stop()

    def _print(self, text: str) -> None:
        if self._p is not None:
            self._p.console.print(text)
        else:
            print(text, flush=True)

    def skip(self, name: str) -> None:
        self._print(f"{name}: finished before, not redone")
        if self._p is not None:
            self._p.advance(self._overall)

    def start(self, name: str, note: str = "") -> None:
        if self._p is not None:
            self.tasks[name] = self._p.add_task(name, total=self.episodes, note=note)
        else:
            self._print(f"{name}: started{' ' + note if note else ''}")

    def advance(self, name: str, episode: int) -> None:
        if self._p is not None and name in self.tasks:
            self._p.update(self.tasks[name], completed=episode)

    def finish(self, name: str, status: str, wall: float, why: str = "") -> None:
        """A run ended; a failed one says why on the terminal too (its last log line), not only in the files.

        :param name: the run's name
        :param status: ``done``, ``failed`` or ``interrupted``
        :param wall: its wall time in seconds
        :param why: for a failed run, the line that says why
        """
        if self._p is not None:
            if name in self.tasks:
                self._p.update(self.tasks[name], note=status, visible=False)
            self._p.advance(self._overall)
        self._print(f"{name}: {status} in {wall:.0f} s" + (f": {why}" if why and status == "failed" else ""))


def last_line(text: str) -> str:
    """The last non-empty line of a run's output (where ``khgrl up`` says why it failed), shortened to one line.

    :param text: the run's output
    """
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[-1][:300] if lines else "no output"
