"""Intervention statistics per episode in the launcher's progress view (live table and --no-progress lines), and
the learner's status read through its typed info."""

from __future__ import annotations

from khgrl.common.wire.messages import ActorInfo, LearnerInfo
from khgrl.common.wire.protocol import EpisodeReport, Status, decode, encode


def _episode(actor, episode, **stats) -> EpisodeReport:
    report = EpisodeReport(actor=actor, stats={"episode": episode, **stats})
    return decode(EpisodeReport, encode(report, actor, episode))


def test_progress_view_counts_interventions_clipping_and_xi(capsys):
    from khgrl.deploy.run.progress import ProgressView
    from rich.console import Console

    view = ProgressView(["a0"], 3, enabled=False)
    view.episode(_episode("a0", 1, ret=-10.0, success=False, interventions=0, intervention_steps=0, clipped_steps=0,
                          mean_abs_xi_h=0.0))
    view.episode(_episode("a0", 2, ret=150.0, success=True, interventions=2, intervention_steps=40, clipped_steps=10,
                          mean_abs_xi_h=0.5))
    view.episode(_episode("a0", 3, ret=-5.0, success=False, interventions=1, intervention_steps=10, clipped_steps=0,
                          mean_abs_xi_h=1.0))
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("[a0] episode 1: return -10.0 success=False interventions=0 (count 0, clipped -")
    assert "interventions=40 (count 2, clipped 25%, mean |xi_h| 0.5)" in out[1]
    row = view.rows["a0"]
    assert (row.done, row.success, row.count, row.steps, row.clipped) == (3, 1, 3, 50, 10)
    console = Console(width=200, record=True)
    console.print(view._table())
    text = console.export_text()
    assert "interventions" in text and "mean" in text and "|xi_h|" in text  # (two-word headers on two lines)
    line = next(ln for ln in text.splitlines() if "a0" in ln)
    # 3 interventions, 50 human steps, 10 clipped (20%), steps-weighted mean |xi_h| (40*0.5 + 10*1.0) / 50 = 0.6
    for cell in ("3/3", "3", "50", "10 (20%)", "0.6"):
        assert cell in line, (cell, line)


def test_progress_view_survives_odd_but_valid_stats(capsys):
    from khgrl.deploy.run.progress import ProgressView

    view = ProgressView([], 2, enabled=False)
    view.episode(_episode("x", 1))  # only the episode number
    view.episode(_episode("x", 2, interventions=1, intervention_steps=0, clipped_steps=3, mean_abs_xi_h=2.0))
    assert view.rows["x"].done == 2
    view._table()


def test_progress_view_reads_the_learner_status_through_its_typed_info():
    from khgrl.deploy.run.progress import ProgressView

    view = ProgressView(["a0"], 2, enabled=False)
    assert view.caption() == "learner: waiting"
    learner = LearnerInfo(id="learner", epoch="e", ingested=120, iterations=15, gradient_steps=96,
                          grad_steps_per_s=12.4, version=3, pending_iterations=0, queue_depth=0, rejects={},
                          paused=False, checkpoints=0, next_seq={"a0": 15}, durable={"a0": -1}, duplicates={},
                          weights_queries=1)
    actor = ActorInfo(id="a0", episode=1, t=5, transitions=5, sent=0, next_seq=0, outbox=0, received=-1, durable=-1,
                      trained=0, weights_version=0, ack_version=0, learner_alive=True, waits=0, wait_s=0.0, resends=0,
                      corrections={}, intervening=False, rejects={}, paused=False, period_ms_p50=1.5)
    view.status(decode(Status, encode(Status(role="actor", info=actor), "a0", 1)))  # not for the caption
    assert view.learner is None
    view.status(decode(Status, encode(Status(role="learner", info=learner), "learner", 1)))
    assert isinstance(view.learner, LearnerInfo)
    assert view.caption() == "learner: 120 transitions, 96 gradient steps (12/s), weights v3"
    assert view.caption(final=True) == "learner: 120 transitions, 96 gradient steps, weights v3"  # no rate once over
