"""Intervention statistics per episode in the launcher's progress view (live table and --no-progress lines)."""

from __future__ import annotations

from common.protocol import decode, encode


def _episode(actor, episode, **stats):
    return decode("episode", encode("episode", actor, episode, actor=actor, stats={"episode": episode, **stats}))


def test_progress_view_counts_interventions_clipping_and_xi(capsys):
    from rich.console import Console

    from deploy.launcher import ProgressView

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
    row = view.actors["a0"]
    assert (row["done"], row["success"], row["count"], row["interventions"], row["clipped"]) == (3, 1, 3, 50, 10)
    console = Console(width=200, record=True)
    console.print(view._table())
    text = console.export_text()
    assert "interventions" in text and "mean |xi_h|" in text
    line = next(ln for ln in text.splitlines() if "a0" in ln)
    # 3 interventions, 50 human steps, 10 clipped (20%), steps-weighted mean |xi_h| (40*0.5 + 10*1.0) / 50 = 0.6
    for cell in ("3/3", "3", "50", "10 (20%)", "0.6"):
        assert cell in line, (cell, line)


def test_progress_view_survives_odd_but_valid_stats(capsys):
    from deploy.launcher import ProgressView

    view = ProgressView([], 2, enabled=False)
    view.episode(_episode("x", 1))  # only the episode number
    view.episode(_episode("x", 2, interventions=1, intervention_steps=0, clipped_steps=3, mean_abs_xi_h=2.0))
    assert view.actors["x"]["done"] == 2
    view._table()
