"""``khgrl human spacemouse`` (human_bridge/spacemouse.py) without a device: synthetic raw HID reports, as a
SpaceMouse sends them, are read by pyspacemouse's own ``SpaceMouseDevice`` from a stand-in HID device
(:class:`~khgrl.human_bridge.spacemouse.ReportReplay`, at easyhid's ``HIDDevice.read`` level) and parsed by the
library (``SpaceMouseDevice._process`` with its ``devices.toml`` layouts); the client turns the parsed state into
pushes (axes, dead zone, hold and toggle buttons) and a :class:`~khgrl.human_bridge.keyboard.PadClient` moves P_h.
The reports and their layouts: tests/spacemouse_reports.py.
"""

from __future__ import annotations

import struct
import sys

import numpy as np
import pytest
from khgrl.human_bridge.spacemouse import COMPACT, ReportReplay, SpaceMouseInput, open_spacemouse
from khgrl.human_bridge.velocity import DEAD_ZONE, Push, dead_zone

from helpers import FakeLink
from spacemouse_reports import FULL, USB_NO_BUTTONS, WIRELESS, buttons, rotation, translation
from test_velocity import _desc, _frame


def _mouse(*reports: bytes, ids: tuple[int, int] = COMPACT, **kw) -> tuple[SpaceMouseInput, ReportReplay]:
    hid = ReportReplay(reports, *ids)
    return SpaceMouseInput(open_spacemouse(hid_devices=[hid]), **kw), hid


def test_the_librarys_parser_turns_raw_reports_into_pushes_along_x_y_z():
    sm, hid = _mouse()
    assert hid.opened and hid.nonblocking and sm.mouse.info.name == "SpaceMouseCompact"
    assert sm.push() == Push() and sm.reports == 0  # nothing sent yet
    hid.add(translation(FULL, -FULL, -FULL))  # right, forward (away from the user), lifted
    assert sm.push() == Push(hold=False, h=1.0, v=1.0, d=1.0) and sm.reports == 1
    hid.add(translation(-201, 120, 2 * FULL))  # left (beyond the dead zone), back, pressed down (beyond full)
    p = sm.push()
    assert p.h == pytest.approx(dead_zone(-201 / FULL)) and p.h == pytest.approx(-0.4992, abs=1e-4)
    assert p.v == pytest.approx(dead_zone(-120 / FULL)) and p.d == -1.0
    hid.add(translation(50, -50, 52))  # 0.143, 0.149 of full deflection: inside the dead zone
    assert sm.push() == Push() and 52 / FULL < DEAD_ZONE
    hid.add(translation(FULL, 0, 0), rotation(FULL, -FULL, FULL))  # a rotation is parsed but moves nothing
    assert sm.push() == Push(h=1.0) and sm.state.roll != 0 and sm.state.yaw != 0
    assert sm.state is sm.mouse.read()  # the state is the library's own (SpaceMouseState)


def test_the_left_button_holds_while_down_and_the_right_one_toggles():
    sm, hid = _mouse(translation(0, -FULL, 0))
    hid.add(buttons(left=True))
    assert sm.push() == Push(hold=True, v=1.0)
    hid.add(buttons())
    assert sm.push() == Push(v=1.0)  # let go: released
    hid.add(buttons(right=True), buttons())  # a click of the right button within one tick: held
    assert sm.push().hold and sm.toggled
    hid.add(buttons(left=True), buttons())  # the left button comes and goes: the toggle stays
    assert sm.push().hold
    hid.add(buttons(right=True))
    assert not sm.push().hold  # clicked again: released
    hid.add(buttons())
    assert not sm.push().hold
    other, hid2 = _mouse(buttons(right=True), hold_button=1, toggle_button=-1)  # the right one holds, no toggle
    assert other.push().hold and other.help.startswith("hold RIGHT +")
    hid2.add(buttons(left=True))
    assert not other.push().hold


def test_every_waiting_report_is_read_in_one_tick_and_the_last_state_stays():
    sm, hid = _mouse(*(translation(k, 0, 0) for k in range(0, 351, 5)))  # 71 reports
    assert sm.poll(limit=10) == 10 and sm.state.x == pytest.approx(45 / FULL)
    assert sm.push().h == 1.0 and sm.reports == 71 and not hid.queue
    assert sm.push().h == 1.0 and sm.reports == 71  # no new report: the cap is where it was


def test_the_wireless_layout_one_13_byte_report():
    sm, hid = _mouse(b"\x01" + struct.pack("<hhhhhh", -FULL, FULL, -FULL, 100, 200, 300), ids=WIRELESS)
    assert sm.mouse.info.name == "SpaceMouseWireless" and sm.mouse.info.bytes_to_read == 13
    assert sm.push() == Push(h=-1.0, v=-1.0, d=1.0)
    hid.add(buttons(left=True))
    assert sm.push().hold


def test_opening_picks_a_supported_device_and_says_why_not_in_one_line(monkeypatch):
    keyboard = ReportReplay(vendor_id=0x046D, product_id=0xC31C)  # some other HID device
    compact, wireless = ReportReplay(), ReportReplay(vendor_id=WIRELESS[0], product_id=WIRELESS[1])
    assert open_spacemouse(hid_devices=[keyboard, wireless, compact]).info.name == "SpaceMouseWireless"
    assert open_spacemouse("SpaceMouseCompact", [keyboard, wireless, compact]).info.name == "SpaceMouseCompact"
    with pytest.raises(RuntimeError, match="^no SpaceMouse: none of the 1 HID devices here"):
        open_spacemouse(hid_devices=[keyboard])
    with pytest.raises(RuntimeError, match="no SpaceMouse model 'Nope'"):
        open_spacemouse("Nope", [compact])
    with pytest.raises(RuntimeError, match="^no SpaceMouse"):  # here: no hidapi library, or no device
        open_spacemouse()
    bare = open_spacemouse(hid_devices=[ReportReplay(vendor_id=USB_NO_BUTTONS[0], product_id=USB_NO_BUTTONS[1])])
    with pytest.raises(RuntimeError, match="no button 0 on the SpaceMouseUSB: it has 0"):
        SpaceMouseInput(bare)
    with pytest.raises(RuntimeError, match="no button 2 on the SpaceMouseCompact: it has 2 .LEFT, RIGHT."):
        SpaceMouseInput(open_spacemouse(hid_devices=[ReportReplay()]), toggle_button=2)
    with pytest.raises(RuntimeError, match="dead zone"):
        SpaceMouseInput(open_spacemouse(hid_devices=[ReportReplay()]), zone=1.0)
    monkeypatch.setitem(sys.modules, "pyspacemouse", None)  # the extra not installed
    with pytest.raises(RuntimeError, match=r"^no SpaceMouse: pyspacemouse is not installed .pip install 'khgrl\[spa"):
        open_spacemouse(hid_devices=[compact])


def test_an_unplugged_device_releases_and_moves_nothing_more(capsys):
    sm, hid = _mouse(buttons(left=True), translation(FULL, 0, 0))
    assert sm.push() == Push(hold=True, h=1.0)
    hid.unplugged = True
    assert sm.push() == Push() and sm.mouse is None and "gone" in sm.help
    assert "the SpaceMouse is gone" in capsys.readouterr().err
    assert sm.push() == Push()


def test_a_report_file_replays_its_reports(tmp_path):
    f = tmp_path / "reports.hex"
    f.write_text("# button 0 down, then right and lifted\n03 01\n01 5e01 0000 a2fe  # x +350, z -350\n\n")
    sm = SpaceMouseInput(open_spacemouse(hid_devices=[ReportReplay.from_file(str(f))]))
    assert sm.push() == Push(hold=True, h=1.0, d=1.0) and sm.reports == 2


def test_on_a_2d_task_the_cap_moves_the_two_view_axes_and_lifting_moves_nothing():
    import time

    from khgrl.human_bridge.keyboard import PadClient

    task = _desc((0.0, 0.0), (1.0, 1.0), third=-1)  # O = 2, no third axis
    sm, hid = _mouse()
    link = FakeLink("sm")
    c = PadClient(link, sm, actor="a0", speed=0.5, name="spacemouse", run="r", task=task, events=lambda: [])
    start = np.array([0.3, 0.5])
    link.queue.append(_frame(start, t=3))
    hid.add(buttons(left=True))
    c.step()
    assert c.hold.holding and link.pub.sent[-1][2:] == (1, 3)
    hid.add(translation(0, -FULL, -FULL))  # forward and lifted: y up, the lift has no axis here
    c.step()
    time.sleep(0.1)
    c.step()
    assert c.hold.p_h.shape == (2,) and c.hold.p_h[0] == start[0] and c.hold.p_h[1] > start[1] + 0.04
    hid.add(buttons())
    c.step()
    assert not c.hold.holding and link.pub.sent[-1][1] is None
