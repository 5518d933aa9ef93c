"""``khgrl human spacemouse`` against real processes, with synthetic raw HID reports instead of a device (read and
parsed by pyspacemouse's own ``SpaceMouseDevice``; the reports: tests/spacemouse_reports.py).

A client in this process, connected to a real router + learner + actor of the 3-D task (test_keyboard_gamepad's
harness), is driven by reports added to its stand-in HID device: the actor's ``corrections.csv`` records the held
P_h moving in the pushed direction along x and the third axis z, then the release. ``khgrl up --human spacemouse``
starts the client itself, its device replaying a file of reports (``KHGRL_SPACEMOUSE_REPORTS``). Without a
SpaceMouse the process exits 3 with one line.
"""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest
from khgrl.human_bridge.spacemouse import REPORTS_ENV, ReportReplay, SpaceMouseInput, open_spacemouse
from test_keyboard_gamepad import (
    OWN,
    OWN_HIGH,
    OWN_LOW,
    _check_moved,
    _drive_real_actor,
    _env,
    _hold_for,
    display,  # noqa: F401  (a fixture)
)

from helpers import REPO, python_main, read_json
from spacemouse_reports import FULL, buttons, rotation, translation


def test_without_a_spacemouse_the_client_exits_3_with_one_line():
    p = subprocess.run(python_main("khgrl.human_bridge.main") + ["spacemouse", "--run", "r", "--connect",
                                                                 "tcp/127.0.0.1:1"], cwd=REPO,
                       env=_env(SDL_VIDEODRIVER="dummy"), capture_output=True, text=True, timeout=60)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 3 and len(lines) == 1 and lines[0].startswith("khgrl human spacemouse: no SpaceMouse"), \
        p.stdout + p.stderr


def test_the_flags_parse():
    from khgrl.human_bridge.main import build_parser

    a = build_parser().parse_args(["spacemouse", "--run", "r", "--task", OWN, "--speed", "0.05"])
    assert (a.client, a.actor, a.id, a.speed, a.device, a.hold_button, a.toggle_button, a.dead_zone) == (
        "spacemouse", "a0", "spacemouse", 0.05, None, 0, 1, 0.15)
    a = build_parser().parse_args(["spacemouse", "--run", "r", "--device", "SpaceNavigator", "--toggle-button", "-1"])
    assert (a.device, a.toggle_button) == ("SpaceNavigator", -1)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["spacemouse", "--run", "r", "--dead-zone", "1"])


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_spacemouse_moves_the_held_p_h_of_a_real_actor(tmp_path, display):  # noqa: F811 (the fixture)
    hid = ReportReplay()
    device = SpaceMouseInput(open_spacemouse(hid_devices=[hid]))

    def script(tick):
        hid.add(buttons(left=True))
        _hold_for(tick, 0.1)
        # right, y inside the dead zone (0.1 toward the user), lifted; a twist of the cap moves nothing
        hid.add(translation(FULL, FULL // 10, -FULL), rotation(FULL, FULL, -FULL))
        _hold_for(tick, 1.0)
        hid.add(translation(0, 0, 0), rotation(0, 0, 0))
        tick()
        hid.add(buttons())
        tick()

    wire, rows, summary, start = _drive_real_actor(tmp_path, display, "spacemouse", device, script)
    _check_moved(wire, rows, summary, up=(0, 2), still=(1,))  # x and z up, y stays
    assert wire[0].episode == start.episode and wire[0].t >= start.t and device.reports == 6


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_up_runs_the_spacemouse_client_on_a_3d_task(tmp_path):
    """khgrl up --human spacemouse: the client khgrl up starts (--config only) reads a file of raw reports through
    the library; the left button stays down and the cap right and lifted, so the hold starts at the first frame it
    sees and ends with the episode."""
    reports = tmp_path / "reports.hex"
    reports.write_text(f"# left button down, then right + lifted\n{buttons(left=True).hex()}\n"
                       f"{translation(FULL, 0, -FULL).hex()}\n")
    run_dir = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "up", "--task", OWN, "--method", "khgrl",
                          "--human", "spacemouse", "--episodes", "1", "--rate", "50", "--learning-starts", "100000",
                          "--max-lead", "100000", "--no-progress", "--run-dir", str(run_dir)], cwd=REPO,
                         env=_env(SDL_VIDEODRIVER="dummy", **{REPORTS_ENV: str(reports)}), capture_output=True,
                         text=True, timeout=200)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    with open(run_dir / "actor-a0" / "corrections.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) >= 20 and {r["client"] for r in rows} == {"spacemouse"}
    steps = [int(r["step"]) for r in rows]
    assert steps == list(range(steps[0], steps[0] + len(steps)))  # one hold, held to the episode's end
    p = np.array([[float(r[f"p_h_{c}"]) for c in "xyz"] for r in rows])
    assert np.all(p >= OWN_LOW) and np.all(p <= OWN_HIGH)
    for k in (0, 2):
        assert np.all(np.diff(p[:, k]) >= 0) and p[-1, k] - p[0, k] > 0.03, p[:, k]
    assert np.all(p[:, 1] == p[0, 1])
    assert read_json(run_dir / "actor-a0" / "summary.json")["corrections"]["holds"] == 1
