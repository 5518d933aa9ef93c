"""The newcomer defects of issue 20 that need no processes (the ones that do: tests/integration/test_newcomer.py):
the launcher's output without a terminal and its last line, the scripted human's task and inputs, messages that
name the real culprit, and the documentation a fresh clone has (no links to the sibling folder of design notes
and the paper that only the project's workspace has, every episodes.csv column, what one seed means)."""

from __future__ import annotations

import dataclasses
import io
import re
import subprocess

import numpy as np
import pytest
from khgrl.common.metrics import EpisodeStats
from khgrl.common.process import StopFlag
from khgrl.common.tasks.api import TaskError, load_task
from khgrl.common.tasks.demos import save_demos
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.common.tasks.world import build_task_world
from khgrl.common.wire.messages import EpisodeReport, Frame
from khgrl.common.wire.protocol import ProtocolError, decode, encode
from khgrl.deploy.examples.own_task import make_task as own_task
from khgrl.deploy.run.outcome import Outcome
from khgrl.deploy.run.progress import ProgressView

from helpers import REPO, RecordingPublisher

OWN = "khgrl.deploy.examples.own_task:make_task"
COLUMNS = ("actor", "episodes", "successes", "last return", "interventions", "human steps", "clipped", "mean |xi_h|")


def _report(episode: int) -> EpisodeReport:
    stats = {"episode": episode, "ret": -201.9, "success": False, "interventions": 1, "intervention_steps": 1200,
             "clipped_steps": 140, "mean_abs_xi_h": 0.123}
    return decode(EpisodeReport, encode(EpisodeReport(actor="a0", stats=stats), "a0", episode))


# ------------------------------------------------------------------ 1. khgrl up's output without a terminal
def test_without_a_terminal_the_view_prints_episode_lines_then_the_whole_table(capsys):
    with ProgressView(["a0"], 1000, enabled=True, tty=False) as view:
        view.episode(_report(1))
        assert capsys.readouterr().out.startswith("[a0] episode 1: return -201.9")  # at once, not at the end
        view.episode(_report(2))
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert out.endswith("\n") and "…" not in out
    assert lines[0].startswith("[a0] episode 2:") and lines[1] == "KhGRL run"
    assert all(c in lines[2] for c in COLUMNS), lines[2]
    assert lines[4].split()[:3] == ["a0", "2/1000", "0"] and lines[5] == "learner: waiting"


def test_the_live_table_fits_80_columns_with_every_header_word_whole():
    from rich.console import Console

    view = ProgressView(["a0", "a1"], 1000, enabled=True, tty=False)
    view.rows["a0"].add(_report(1000).stats)
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(view._table())
    text = console.export_text()
    assert "…" not in text and max(len(ln.rstrip()) for ln in text.splitlines()) <= 80
    words = set(text.split())
    assert all(w in words for c in COLUMNS for w in c.split()), text
    assert "1000/1000" in text and "140 (12%)" in text


# ---------------------------------------------------------------------------- 2. "interrupted" said
def test_the_last_line_says_how_the_run_ended():
    from khgrl.deploy.run.outcome import ending, final_line

    flag = StopFlag()
    assert ending(Outcome(), flag) == "finished"
    assert ending(Outcome(failed=["learner"]), flag) == "failed (learner)"
    assert ending(Outcome(failed=["timeout"]), flag) == "timed out"
    assert ending(Outcome(stopped_by="x"), flag) == "stopped from elsewhere"
    flag.set("SIGINT")
    line = final_line(Outcome(), flag, 39.4, {"a0": 0}, "runs/x")
    assert line == "khgrl up: interrupted (SIGINT) after 39 s; exit codes {'a0': 0}; results in runs/x"


# ---------------------------------------------------------------- 3. the scripted human's task
@pytest.fixture(scope="module")
def own_descriptor():
    return KGRLEnv(own_task()).descriptor(OWN)


def test_a_scripted_human_follows_the_announced_task_or_refuses_in_one_line(own_descriptor):
    from khgrl.common.config.settings import RunConfig
    from khgrl.human_bridge.scripted import announced_task

    said: list[str] = []
    task = announced_task(own_descriptor, RunConfig(), said.append)  # its own settings: the passage world
    assert task.name == "point-3d" and task.scripted_human is not None
    assert said == [f"khgrl human scripted: the actor runs task {OWN!r}; following it (this client's settings said "
                    "'passage:high_cov')"]
    for spec, reason in [("no_such_module_h3:make", "which this client cannot load"),
                         ("passage:low_cov", "here that spec gives task 'passage-low_cov'")]:
        with pytest.raises(TaskError, match=reason) as info:
            announced_task(dataclasses.replace(own_descriptor, spec=spec), RunConfig(), said.append)
        assert "\n" not in str(info.value)


# ------------------------------------------------------- 6./7./11. messages that name the real culprit
def test_demos_of_another_o_name_the_demonstrations_file(tmp_path):
    path = save_demos(tmp_path / "passage.npz", np.random.default_rng(0).random((3, 50, 2)))
    with pytest.raises(TaskError) as info:
        build_task_world(load_task(OWN, path))
    text = str(info.value)
    assert f"the demonstrations in {path} have O = 2 outputs per step" in text and "this task's command has 3" in text
    assert "workspace low needs" not in text


def test_infeasible_constraints_name_the_contradicting_rows_and_whose_they_are():
    contradict = (np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0]]), np.array([0.5, 0.0, -0.4]))  # x >= .5, x <= .4
    with pytest.raises(TaskError) as info:
        build_task_world(dataclasses.replace(own_task(), constraints=contradict))
    text = str(info.value)
    assert "rows 0..5 are the workspace box, rows 6..8 are your constraints" in text, text
    rows = re.findall(r"row (\d+), ", text)
    assert rows == ["6", "8"], text  # your rows 0 and 2; row 1 (y >= 0) is innocent
    assert "your constraint 0" in text and "your constraint 2" in text and "G=" not in text
    with pytest.raises(TaskError, match=r"row 3, workspace high of output 0: \[-1.0, 0.0, 0.0\] . P >= -0.98; "
                                        r"row 6, your constraint 0"):
        build_task_world(dataclasses.replace(own_task(), constraints=(np.array([[1.0, 0, 0]]), np.array([2.0]))))


def test_a_task_without_demos_runs_with_demos_and_says_so_without(tmp_path):
    from khgrl.deploy.examples.own_task import make_demos

    bare = dataclasses.replace(own_task(), demos=None)
    with pytest.raises(TaskError, match="Task.demos is None, so give --demos FILE"):
        build_task_world(bare)
    path = save_demos(tmp_path / "d.npz", make_demos(m=4, seed=1))
    assert build_task_world(bare.with_demos(path)).demos.shape == (4, 200, 3)


# ---------------------------------------------------------------- 12. what a scripted human gets
def test_scripted_human_inputs_are_read_from_its_signature():
    from khgrl.common.tasks.api import call_scripted_human, scripted_human_inputs

    def old(mean):
        return None

    def some(mean, position, *, phase):
        return None

    def every(mean, **kw):
        return None

    assert scripted_human_inputs(old) == ()
    assert scripted_human_inputs(some) == ("phase", "position")
    assert scripted_human_inputs(every) == ("step", "phase", "position", "obs")
    got = []
    call_scripted_human(lambda m, step, obs: got.append((step, obs)), np.zeros(2), step=4, phase=0.5,
                        position=np.ones(2), obs=np.arange(3.0))
    assert got[0][0] == 4 and list(got[0][1]) == [0.0, 1.0, 2.0]


def test_the_build_check_calls_a_scripted_human_with_step_phase_and_position():
    seen = []

    def reacts_to_the_robot(mean, *, step, phase, position, obs):
        seen.append((step, phase, np.array(position), obs))
        return None if position[0] < 0.5 else mean

    world = build_task_world(dataclasses.replace(own_task(), scripted_human=reacts_to_the_robot))
    n = world.demos.shape[1]
    assert [s[0] for s in seen] == list(range(n)) and seen[-1][1] == pytest.approx(1.0) and seen[0][1] == 0.0
    assert all(s[3] is None for s in seen)
    np.testing.assert_array_equal(seen[7][2], world.model.grid_mean[7])  # the robot taken at the mean


def test_the_scripted_client_passes_the_frames_robot_observation_and_phase():
    from khgrl.human_bridge.scripted import ScriptedAnswers, ScriptedHuman, ScriptedHumanConfig

    seen = []

    def guide(mean, *, step, phase, position, obs):
        seen.append((step, phase, None if position is None else position.tolist(),
                     None if obs is None else obs.tolist()))
        return position + 0.01

    answers = ScriptedAnswers(ScriptedHuman(guide, ScriptedHumanConfig(episodes=(2,))), RecordingPublisher(),
                              horizon=11)
    for ep, t in ((1, 0), (2, 0), (2, 1)):
        raw = Frame(actor="a0", episode=ep, t=t, phase=t / 10, robot=np.array([0.3, 0.4]),
                    desired=np.zeros(2), mean=np.full(2, t / 10), scale=np.ones(2), intervening=False, task="x",
                    next_mean=np.full(2, (t + 1) / 10), obs=np.array([0.3, 0.4, 7.0]))
        answers.frame(decode(Frame, encode(raw, "a0", t)))  # obs crosses the wire
    # the announcement of episode 2's step 0 (before the episode: the robot at the mean, no observation), then
    # a word for steps 1 and 2 from the frames of steps 0 and 1
    assert seen[0] == (0, 0.0, [0.0, 0.0], None)
    assert seen[1] == (1, pytest.approx(0.1), [0.3, 0.4], [0.3, 0.4, 7.0])
    assert seen[2][:2] == (2, pytest.approx(0.2))
    assert [s[4] for s in answers.pub.sent] == [0, 1, 2]


def test_a_frames_observation_is_checked_on_receipt():
    raw = Frame(actor="a0", episode=1, t=0, phase=0.0, robot=np.zeros(2), desired=np.zeros(2), mean=np.zeros(2),
                scale=np.ones(2), intervening=False, task="x", obs=np.zeros(300))
    with pytest.raises(ProtocolError, match="obs"):
        decode(Frame, encode(raw, "a0", 0))
    assert decode(Frame, encode(raw.replace(obs=None), "a0", 0)).obs is None


def test_the_single_process_wrapper_gives_the_scripted_human_the_robot():
    from khgrl.human_bridge.scripted import HumanCorrectionWrapper, ScriptedHuman, ScriptedHumanConfig

    seen = []

    def guide(mean, *, step, position, obs):
        seen.append((step, position.copy(), obs.copy()))
        return None

    env = HumanCorrectionWrapper(KGRLEnv(own_task()), ScriptedHuman(guide, ScriptedHumanConfig(episodes=(1,))))
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros(3, dtype=np.float32))
    assert [s[0] for s in seen] == [0, 1, 2]
    np.testing.assert_array_equal(seen[2][1], env.unwrapped.trail[2])  # the robot before step 2
    np.testing.assert_array_equal(seen[2][2], seen[2][1])  # the example's observation is the robot position


# ------------------------------------------------------------------------- 10./13./14. the docs
def _tracked() -> list[str]:
    out = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    return out.split()


def test_no_tracked_file_links_outside_the_clone():
    needle = "../" + "shared"  # (spelled so that this file does not contain it)
    bad = []
    for name in _tracked():
        path = REPO / name
        if path.suffix in {".png", ".gif", ".npz", ".zip", ".pkl"} or not path.is_file():
            continue
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue
        bad += [f"{name}:{i}" for i, ln in enumerate(text.splitlines(), 1) if needle in ln]
    assert not bad, f"links to {needle}, which a clone does not have: {bad}"
    assert (REPO / "docs" / "method.md").is_file() and "docs/method.md" in (REPO / "README.md").read_text()
    method = (REPO / "docs" / "method.md").read_text()
    assert "Kernelized human-Guided Reinforcement Learning" in method
    for eq in ("(eq. 4)", "(eq. 6)", "A = (K + γΣ)⁻¹"):
        assert eq in method


def test_every_episodes_csv_column_is_documented():
    readme = (REPO / "docs" / "guide" / "runtime.md").read_text()
    table = readme[readme.index("## episodes.csv"):]
    table = table[:table.index("\n\n", table.index("| column |"))]
    documented = re.findall(r"^\| `(\w+)` \|", table, re.MULTILINE)
    written = list(EpisodeStats(episode=1).to_row())  # what actor/results.py appends (append_episode_row)
    assert documented == written, (documented, written)


def test_the_readme_says_what_one_seed_gives_and_results_say_where_numbers_come_from():
    readme = (REPO / "README.md").read_text()
    assert "one seed is not a result" in readme and "82 % ± 18 %" in readme
    results = (REPO / "docs" / "results.md").read_text()
    section = results[results.index("## Repeatability"):results.index("## What is kept")]
    for fact in ("282f924", "repeats exactly on one machine", "diverge on another machine", "set_num_threads",
                 "use_deterministic_algorithms", "2 shared x86-64"):
        assert fact in section, fact


def test_simulation_mode_does_not_report_its_lock_step_waits_as_holds(capsys):
    """Issue 36: a 15-episode simulation run printed 104 "robot held: waiting for the learner" / "robot released"
    lines, the schedule of lock-step training, against 23 useful ones. Simulation mode now says only holds that are
    news (and their release); robot mode says every hold."""
    from khgrl.common.wire.messages import Status
    from khgrl.common.wire.status import ActorInfo

    def status(held: str) -> Status:
        return Status(role="actor", info=ActorInfo(
            id="a0", episode=1, t=5, transitions=5, sent=0, next_seq=0, outbox=0, received=-1, durable=-1, trained=0,
            weights_version=0, ack_version=0, learner_alive=True, waits=0, wait_s=0.0, resends=0, corrections={},
            intervening=False, rejects={}, paused=bool(held), period_ms_p50=None, held=held))

    helds = ["waiting for the learner (1.2 s)", "", "waiting for the learner (0.6 s)", "",
             "e-stop by launcher", "", "waiting for the learner (0.7 s)", ""]
    for quiet in (True, False):
        view = ProgressView(["a0"], 10, enabled=False, tty=False, schedule_quiet=quiet)
        for held in helds:
            view.status(status(held))
        lines = capsys.readouterr().out.splitlines()
        if quiet:
            assert lines == ["[a0] robot held: e-stop by launcher", "[a0] robot released"]
        else:
            assert len(lines) == 8 and lines[0] == "[a0] robot held: waiting for the learner (1.2 s)"
