"""What a new user met (issue 20, "Newcomer defects"), each against the real processes:

* ``khgrl up ... > log`` (stdout not a terminal): a plain line per episode as episodes end, the final table whole,
  every line ended; after Ctrl-C the last line and summary.json say "interrupted";
* ``khgrl human scripted`` started by hand without ``--task`` helps with the task the actor announces (here the
  3-D example task, not the passage world it used to take silently);
* ``khgrl eval`` on that hand-started run (no ``RUN_DIR/config.json``) and on its actor folder, with the scale the
  actor learned;
* a Fetch command prints no AdroitHand notice.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from helpers import REPO, SMALL, ProcGroup, read_json, unique_run
from launch import Launcher, _rows

pytestmark = pytest.mark.integration

OWN_TASK = "khgrl.deploy.examples.own_task:make_task"
COLUMNS = ("actor", "episodes", "successes", "last return", "interventions", "human steps", "clipped", "mean |xi_h|")


# ========================================================== 1./2. output to a file, then Ctrl-C
@pytest.mark.timeout(300)
def test_output_to_a_file_has_a_line_per_episode_a_whole_table_and_says_interrupted(tmp_path):
    """The default (``--progress``) with stdout a file: episode lines while the run goes on (not only at the end),
    then on Ctrl-C (SIGINT to the launcher's process group, as a terminal sends it) the table in plain text with
    every header whole, the last line on a line of its own saying the run was interrupted."""
    up = Launcher(tmp_path, tmp_path / "run", "--scenario", "low_cov", "--learning-starts", "64", "--method", "kgrl",
                  "--human", "none", "--episodes", "1000", "--max-lead", "100000", "--rate", "100", *SMALL)
    try:
        up.wait_line("[a0] episode 1:", 180)  # while khgrl up still runs (wait_line checks it)
        os.killpg(up.proc.pid, signal.SIGINT)
        rc = up.proc.wait(timeout=60)
        out = up.stdout
        assert rc == 130, f"exit code {rc}\n{out}\n{up.stderr}"
        lines = out.splitlines()
        assert out.endswith("\n") and "…" not in out, out
        header = next((ln for ln in lines if ln.lstrip().startswith("actor ")), None)
        assert header is not None and all(c in header for c in COLUMNS), out
        table = lines.index(header)
        assert lines[table - 1] == "KhGRL run" and lines[table + 2].split()[0] == "a0", out
        assert any(ln.startswith("learner: ") for ln in lines[table:]), out
        assert lines[-1].startswith("khgrl up: interrupted (SIGINT) after "), lines[-1]
        assert not any("khgrl up: " in ln and not ln.startswith("khgrl up: ") for ln in lines), out
        summary = read_json(up.run_dir / "summary.json")
        assert summary["interrupted"] is True and summary["ended"] == "interrupted (SIGINT)", summary
    finally:
        up.cleanup()


# =========================================== 3./4. a hand-started scripted human, then khgrl eval
@pytest.fixture(scope="module")
def by_hand(tmp_path_factory):
    """Router, learner, actor (the 3-D example task, KhGRL) and ``khgrl human scripted`` started by hand with one
    ``--run-dir``; the human (started first, without ``--task``) helps in episode 2."""
    base = tmp_path_factory.mktemp("by_hand")
    run, run_dir = unique_run(), base / "run"
    with ProcGroup(base) as g:
        ep = g.router()
        human = g.human(run, ep, "scripted", "--human-episodes", "2")
        learner = g.learner(run, ep, "--learning-starts", "100", "--checkpoint-every", "0")
        actor = g.actor(run, ep, "--task", OWN_TASK, "--method", "khgrl", "--episodes", "2", "--learning-starts",
                        "100", "--max-lead", "100000", "--rate", "100")
        rc = actor.wait(200)
        assert rc == 0, actor.tail()
        assert learner.stop(60) == 0, learner.tail()
        human_rc = human.stop(30)
        human_log = human.tail(200)
    return run_dir, human_rc, human_log


@pytest.mark.timeout(400)
def test_a_scripted_human_started_by_hand_takes_the_actors_task(by_hand):
    run_dir, human_rc, log = by_hand
    assert human_rc == 0 and "Traceback" not in log, log
    assert "the actor runs task 'khgrl.deploy.examples.own_task:make_task'; following it" in log, log
    rows = _rows(run_dir)
    assert [int(r["intervention_steps"]) > 0 for r in rows] == [False, True], rows


@pytest.mark.timeout(400)
def test_eval_on_a_hand_started_run_and_on_its_actor_folder_uses_the_learned_scale(by_hand, capsys):
    from khgrl.deploy.cli import main as khgrl

    run_dir = by_hand[0]
    assert not (run_dir / "config.json").exists()  # no khgrl up: the settings are the actor's
    scale = read_json(run_dir / "actor-a0" / "scale_model.json")
    assert scale["n_updates"] > 0 and scale["x"], scale  # refitted from the human of episode 2
    rc = khgrl(["eval", str(run_dir), "--episodes", "1"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "task point-3d" in out.out and "scale learned by actor-a0" in out.out and "warning" not in out.out, out.out
    assert (run_dir / "eval" / "eval.csv").is_file()
    # the actor folder (what a user tried instead) is the same run and actor, its settings the same file
    from khgrl.deploy.tools.evaluate import find_run, read_config

    assert find_run(run_dir / "actor-a0") == (run_dir, "a0")
    assert read_config(run_dir, "a0")[2] == run_dir / "actor-a0" / "config.json"


# ============================================================================= 9. Fetch is quiet
@pytest.mark.timeout(120)
def test_a_fetch_command_prints_no_adroit_hand_notice():
    code = "from khgrl.common.tasks.api import load_task; load_task('fetch:moved').make_env(0).close(); print('built')"
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=100)
    assert proc.returncode == 0 and "built" in proc.stdout, proc.stderr
    assert "AdroitHand" not in proc.stderr, proc.stderr
