"""How a ``khgrl up`` ended: the :class:`Outcome`, ``RUN_DIR/summary.json``, the failure report and the exit code.

An actor's alarm in its status (:func:`actor_alarm`: another process publishes as it, two learners run) and an
actor that exits because another process publishes as it (:func:`process_error`) end the run with that line as its
``error`` (exit 1)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field

from khgrl.common.delivery.actor_guard import SPLIT_EXIT
from khgrl.common.process import StopFlag
from khgrl.deploy.run.supervisor import Proc, ProcessGroup

__all__ = ["Outcome", "write_summary", "report_failures", "exit_code", "ending", "final_line", "actor_alarm",
           "process_error"]


@dataclass
class Outcome:
    """How a run ended."""

    failed: list[str] = field(default_factory=list)  # process names, or "timeout"
    stopped_by: str = ""  # a stop command from elsewhere
    error: str = ""  # e.g. the router unreachable
    rejects: dict = field(default_factory=dict)


def actor_alarm(out: Outcome, status, key: str) -> None:
    """An actor's (or the learner's: two different batches signed by one actor for one seq) status with an alarm
    ends the run: the alarm becomes the run's error (once, said on stderr).

    :param out: how the run ends
    :param status: a decoded status message
    :param key: the key it came on
    """
    alarm = getattr(status.info, "alarm", "")
    if status.role not in ("actor", "learner") or not alarm or out.error:
        return
    out.error = f"{status.role} {status.info.id}: {alarm}"
    print(f"khgrl up: error: {out.error} (status on {key}); ending the run", file=sys.stderr, flush=True)


def process_error(out: Outcome, proc: Proc) -> None:
    """An actor that exited because another process publishes as it: its error line becomes the run's error.

    :param out: how the run ends
    :param proc: the process that exited
    """
    if proc.returncode != SPLIT_EXIT or out.error:
        return
    lines = [ln for ln in proc.text().splitlines() if ln.startswith(f"khgrl actor {proc.name}: error:")]
    if lines:
        out.error = lines[-1].split(": error: ", 1)[1]
        out.error = f"actor {proc.name}: {out.error}"


def ending(out: Outcome, flag: StopFlag) -> str:
    """How the run ended, in words: ``interrupted (SIGINT)``, ``failed (learner)``, ``timed out``, ``stopped from
    elsewhere``, ``ended with an error`` or ``finished``.

    :param out: how the run ended
    :param flag: the launcher's stop flag (set by SIGINT/SIGTERM)
    """
    if flag:
        return f"interrupted ({flag.reason})" if flag.reason else "interrupted"
    if out.failed == ["timeout"]:
        return "timed out"
    if out.failed:
        return f"failed ({', '.join(n for n in out.failed if n != 'timeout')})"
    if out.stopped_by:
        return "stopped from elsewhere"
    return "ended with an error" if out.error else "finished"


def final_line(out: Outcome, flag: StopFlag, wall: float, codes: dict, run_dir) -> str:
    """The last line of ``khgrl up``: how the run ended, after how long, the exit codes and where the results are.

    :param out: how the run ended
    :param flag: the launcher's stop flag
    :param wall: wall time in seconds
    :param codes: exit code by process name
    :param run_dir: the run directory
    """
    return f"khgrl up: {ending(out, flag)} after {wall:.0f} s; exit codes {codes}; results in {run_dir}"


def write_summary(plan, group: ProcessGroup, out: Outcome, wall: float, interrupted: bool, ended: str = "") -> dict:
    """``RUN_DIR/summary.json``: exit codes, failures, wall time, how the run ended and each actor's own summary.

    :param plan: the run's plan
    :param group: the run's processes (exited)
    :param out: how the run ended
    :param wall: wall time in seconds
    :param interrupted: stopped by SIGINT/SIGTERM
    :param ended: how it ended in words (:func:`ending`)
    """
    summary = {"run": plan.run_id, "wall_time_s": wall, "exit_codes": {p.name: p.returncode for p in group.procs},
               "ended": ended or ("interrupted" if interrupted else "finished"),
               "failed": out.failed, "interrupted": interrupted, "stopped_by": out.stopped_by or None,
               "error": out.error or None, "resumed": plan.resume, "launcher_rejects": out.rejects}
    for aid in plan.cfg.actor_ids():
        path = plan.run_dir / f"actor-{aid}" / "summary.json"
        try:
            summary[aid] = json.loads(path.read_text())
        except (OSError, ValueError):
            pass
    (plan.run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def report_failures(group: ProcessGroup, out: Outcome) -> None:
    """Each failed process's exit code and the tail of its log, on stderr."""
    for p in group.procs:
        if p.name in out.failed:
            print(f"khgrl up: process {p.name} exited with code {p.returncode}; last lines of {p.log_path}:\n"
                  f"{p.tail(20)}", file=sys.stderr)
    if out.error:
        print(f"khgrl up: error: {out.error}", file=sys.stderr)


def exit_code(out: Outcome, flag: StopFlag) -> int:
    """0 done, 1 failed or stopped from elsewhere, 128 + signal on SIGINT/SIGTERM."""
    if flag:
        return 143 if flag.reason == "SIGTERM" else 130
    return 1 if out.failed or out.stopped_by or out.error else 0
