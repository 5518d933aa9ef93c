"""The runtime benchmark's results as one table (rich) and a note on the machine's load."""

from __future__ import annotations

import os

__all__ = ["results_table", "load_note"]


def _ms3(d: dict | None) -> str:
    if not d or d.get("p50") is None:
        return "-"
    return f"{d['p50']:.1f} / {d['p99']:.1f} / {d['max']:.1f} ms"


def _met(ok: bool) -> str:
    return "met" if ok else "NOT met"


def _ingest_rows(table, r: dict, batch: int, inflight: int) -> None:
    ing, ingc = r["ingest"], r["ingest_ckpt"]
    base = ing["transitions_per_s"]
    table.add_row("1. learner ingest, no durability", f"{base:,.0f} transitions/s", "",
                  f"{ing['transitions']} in {ing['elapsed_s']:.2f} s, batches of {batch}, ≤ {inflight} unacked")
    if "ingest_signed" in r:
        rate = r["ingest_signed"]["transitions_per_s"]
        table.add_row("1. … signed per role (run-key mac + Ed25519)", f"{rate:,.0f} transitions/s", f"{base:,.0f} /s",
                      f"{rate / base:.0%} (the learner checks each batch's mac and actor signature)")
    if "ingest_journal" in r:
        ij = r["ingest_journal"]
        rate = ij["durable_transitions_per_s"]
        table.add_row("1. … with the journal (to the last durable ack)", f"{rate:,.0f} transitions/s",
                      f"{base:,.0f} /s", f"{rate / base:.0%} (target ≥ 50 %: {_met(rate >= 0.5 * base)}); "
                      f"{ij['learner_checkpoints']} full checkpoints (buffer {ij['buffer_size']}); "
                      f"{ij['transitions_per_s']:,.0f} /s to the last received ack")
    table.add_row("1. … no journal, full checkpoint every 2000", f"{ingc['transitions_per_s']:,.0f} transitions/s",
                  f"{base:,.0f} /s", f"{ingc['transitions_per_s'] / base:.0%} "
                  f"({ingc['learner_checkpoints']} checkpoints; the last batch durable only at the end)")


def _actor_rows(table, r: dict, rate: float, rt_priority: int) -> None:
    act, ref = r["actor"], r["reference"]
    wl, lp = act["weights_latency_ms"], act["loop_period_ms"]
    table.add_row("2. weights publish → applied by actor (p50/p99/max)", _ms3(wl), "",
                  f"{wl['n']} of {act['weights_versions_published']} versions applied (newest wins)")
    table.add_row(f"3. actor loop period @ {rate:g} Hz (p50/p99/max)", _ms3(lp), f"target {1e3 / rate:.1f} ms",
                  f"{lp['n']} steps; learner trained {act['learner_gradient_steps']} gradient steps meanwhile")
    if "actor_rt" in r:
        rt = r["actor_rt"]
        lpr = rt["loop_period_ms"]
        note = (f"p99 {lpr['p99'] - 1e3 / rate:+.1f} ms from target (target ≤ +2 ms: "
                f"{_met(lpr['p99'] - 1e3 / rate <= 2.0)})") if rt["realtime"] else \
            "SCHED_FIFO refused (not root / no CAP_SYS_NICE): normal scheduling"
        table.add_row(f"3b. … control loop under SCHED_FIFO {rt_priority} (p50/p99/max)", _ms3(lpr),
                      f"target {1e3 / rate:.1f} ms", note)
    gap = ref["step_gap_ms"]
    table.add_row("3. single-process SB3: env.step gap (p50/p99/max)", _ms3(gap), "",
                  f"pause p99 {gap['p99']:.0f} ms vs actor period p99 {lp['p99']:.1f} ms "
                  f"({gap['p99'] / lp['p99']:.1f}×)")


def _train_rows(table, r: dict) -> None:
    tr = r["train"]
    table.add_row("4. learner gradient steps/s (backlog)", f"{tr['learner_grad_steps_per_s']:.1f} /s",
                  f"{tr['standalone_grad_steps_per_s']:.1f} /s standalone",
                  f"{tr['ratio']:.0%} (target ≥ 100 %: {_met(tr['ratio'] >= 1.0)})")
    if tr["learner_train_call_grad_steps_per_s"]:
        lc, sc = tr["learner_train_call_grad_steps_per_s"], tr["standalone_train_call_grad_steps_per_s"]
        table.add_row("4. … median train() call alone (8 steps)", f"{lc:.1f} /s", f"{sc:.1f} /s standalone",
                      f"{lc / sc:.0%} (without the loop: weights publish, acks, logging)")


def results_table(record: dict):
    """A rich table of a finished benchmark record.

    :param record: what :func:`khgrl.benchmarks.runtime.run.run_runtime_benchmark` returns
    """
    from rich.table import Table

    r, cfg = record["results"], record["config"]
    table = Table(title="KhGRL runtime (one run, same machine)")
    for col, justify in (("measurement", "left"), ("value", "right"), ("compared with", "right"),
                         ("ratio / note", "left")):
        table.add_column(col, justify=justify)
    _ingest_rows(table, r, cfg["batch"], cfg["inflight"])
    _actor_rows(table, r, cfg["rate_hz"], cfg["rt_priority"])
    _train_rows(table, r)
    if "kill_resume" in r:
        kr = r["kill_resume"]
        table.add_row("5. learner SIGKILL + resume", f"{kr['lost']} lost, {kr['duplicated']} duplicated",
                      f"{kr['actor_transitions']} transitions",
                      f"killed with {kr['killed_at_journaled']} in the journal, no full checkpoint; "
                      f"{kr['actor_resends']} re-sends")
    return table


def load_note(record: dict) -> str:
    """What the numbers are worth on this machine (load average at start and end, wall time)."""
    machine = record["machine"]
    return (f"Machine: {os.cpu_count()} CPUs shared with other jobs; load average (1/5/15 min) "
            f"{machine['load_start']} at start, {machine['load_end']} at end. Absolute numbers are noisy; each "
            f"ratio compares values measured in this one run, minutes apart, under the same load. Wall time "
            f"{record['wall_s']:.0f} s.")
