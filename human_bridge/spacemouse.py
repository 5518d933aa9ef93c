"""``khgrl human spacemouse``: correct an actor with a 3Dconnexion SpaceMouse (6-DoF puck), for any task.

The same window and hold logic as ``khgrl human keyboard`` and ``gamepad`` (:func:`khgrl.human_bridge.keyboard.run_pad`,
:class:`~khgrl.human_bridge.velocity.VelocityHold`); the SpaceMouse (:class:`SpaceMouseInput`):

* **left button** (``--hold-button``: button 0 of the library's list for the model), held -- hold the robot: P_h
  starts at its desired position and the cap moves it; letting go releases it. Held, not toggled: as with the
  gamepad's button, and as in HIL-SERL, where an intervention lasts exactly while the operator acts on the
  SpaceMouse, the hand leaving the device hands the robot back (a dead-man switch). The **right button**
  (``--toggle-button``) toggles a hold instead (press once to hold, again to release), as Enter does for the
  keyboard, for one-handed use.
* **cap right / left** (the device's x) -- P_h along the main view's horizontal axis (``view_axes[0]``);
  **push forward / pull back** (y, away from you = +) -- along its vertical axis (``view_axes[1]``);
  **lift / press down** (z, up = +) -- along the third axis (``view_third``; z of a 3-D task such as
  ``fetch:moved``; nothing for a task with O = 2). The further the cap is pushed, the faster; full deflection (the
  library's 1.0, a raw count of 350) moves at ``--speed``. Rotations are not used.
* A dead zone (``--dead-zone``, default 0.15 of full deflection) around rest is no push. q or Esc in the window, or
  closing it, quits (releasing first); a failed read (the device unplugged) releases, and the cap does nothing more.

Input comes through the library's own read path: pyspacemouse (``khgrl[spacemouse]``) enumerates HID devices
with easyhid (hidapi) and matches them to its model table (``devices.toml``); :func:`open_spacemouse` hands the
matched HID device to the library's :class:`pyspacemouse.SpaceMouseDevice` (Z-up axes: ``AxisConvention.HID_Z_UP``),
whose ``read`` takes one raw report from the HID device and parses it (``SpaceMouseDevice._process``: report 1
translation, 2 rotation, 3 buttons on most models; one 13-byte report 1 for both on the wireless ones). Every tick
reads until no report waits.

Exit code 3 with one line when there is no display, pyspacemouse or the hidapi library is missing (Debian:
``apt install libhidapi-hidraw0``; reading ``/dev/hidraw*`` may need a udev rule), or no supported SpaceMouse is
connected (``--device`` picks a model by the library's name when there are several).

Without a device: ``KHGRL_SPACEMOUSE_REPORTS=FILE`` replaces the HID enumeration with one :class:`ReportReplay`, a
SpaceMouse Compact whose reads return the file's raw reports (hex bytes, one report a line, ``#`` comments), then
nothing, so that the last state stays (button down, cap pushed) -- how the tests run this client under ``khgrl up``.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import deque
from typing import Iterable, Sequence

from khgrl.common.config.process import ProcessConfig
from khgrl.human_bridge import keyboard
from khgrl.human_bridge.hid_devices import REPORTS_ENV, check_spacemouse
from khgrl.human_bridge.velocity import DEAD_ZONE, Push, dead_zone

__all__ = ["SpaceMouseInput", "ReportReplay", "open_spacemouse", "add_arguments", "run", "HOLD_BUTTON",
           "TOGGLE_BUTTON", "REPORTS_ENV", "COMPACT", "MAX_READS"]

HOLD_BUTTON, TOGGLE_BUTTON = 0, 1  # LEFT and RIGHT on the two-button models (Compact, Navigator, Wireless)
COMPACT = (0x256F, 0xC635)  # a SpaceMouse Compact's USB vendor and product id (the library's devices.toml)
MAX_READS = 1000  # reports read in one tick at most (a device sends ~125 a second)
NO_LIBRARY = "no SpaceMouse: pyspacemouse is not installed (pip install 'khgrl[spacemouse]')"


class SpaceMouseInput:
    """A SpaceMouse's cap and buttons, as a :class:`~khgrl.human_bridge.velocity.Push` (see the module docstring).

    :param mouse: the opened :class:`pyspacemouse.SpaceMouseDevice` (:func:`open_spacemouse`).
    :param hold_button: the button (index in the library's list for the model) that holds the robot while down.
    :param toggle_button: the button that toggles a hold (negative: none).
    :param zone: the cap's dead zone, a fraction of full deflection.
    """

    def __init__(self, mouse, hold_button: int = HOLD_BUTTON, toggle_button: int = TOGGLE_BUTTON,
                 zone: float = DEAD_ZONE) -> None:
        info = mouse.info
        count = len(info.button_specs)
        bad = hold_button if not 0 <= hold_button < count else toggle_button if toggle_button >= count else None
        if bad is not None:  # a negative toggle button is none; the hold button is needed
            raise RuntimeError(f"no button {bad} on the {info.name}: it has {count} "
                               f"({', '.join(info.button_names) or 'none'})")
        if not 0.0 <= zone < 1.0:
            raise RuntimeError(f"the dead zone must be in [0, 1), not {zone}")
        self.mouse, self.hold_button, self.toggle_button, self.zone = mouse, hold_button, toggle_button, zone
        self.state = None  # the library's SpaceMouseState, once a report came
        self.reports = 0  # reports parsed by the library
        self.toggled, self._toggle_down = False, False
        hold = info.get_button_name(hold_button)
        toggle = f" ({info.get_button_name(toggle_button)}: toggle)" if toggle_button >= 0 else ""
        self.help = f"hold {hold}{toggle} + move the cap; lift/press: third axis; q: quit"
        mouse.configure(callback=self._parsed)

    def _parsed(self, state) -> None:
        """The library parsed one report (its callback): count it, and catch every press of the toggle button."""
        self.reports += 1
        self.state = state
        down = self._button(self.toggle_button)
        if down and not self._toggle_down:
            self.toggled = not self.toggled
        self._toggle_down = down

    def _button(self, index: int) -> bool:
        return self.state is not None and 0 <= index < len(self.state.buttons) and bool(self.state.buttons[index])

    def handle(self, event) -> bool:
        """Take one pygame event of the window; True asks to quit (q, Esc, the window closed).

        :param event: a pygame event.
        """
        return keyboard.quit_event(event)

    def poll(self, limit: int = MAX_READS) -> int:
        """Read (and let the library parse) the reports waiting, at most ``limit``; the number parsed. A failed read
        forgets the device (:meth:`clear`).

        :param limit: the most reads in one call.
        """
        from easyhid import HIDException

        before = self.reports
        try:
            for k in range(limit if self.mouse is not None else 0):
                self.mouse.read()
                if self.reports == before + k:  # this read parsed nothing: no report waits
                    break
        except (HIDException, OSError) as exc:
            print(f"khgrl human spacemouse: the SpaceMouse is gone ({exc}): released", file=sys.stderr, flush=True)
            self.clear()
        return self.reports - before

    def clear(self) -> None:
        """Forget the device and its state (it went away): no hold, no push from now on."""
        self.mouse, self.state, self.toggled, self._toggle_down = None, None, False, False
        self.help = "the SpaceMouse is gone: restart the client to use it again; q: quit"

    def push(self) -> Push:
        """The device's state now, after reading the waiting reports (x right, y forward, z up are +)."""
        self.poll()
        s = self.state
        if s is None:
            return Push()
        return Push(hold=self._button(self.hold_button) or self.toggled, h=dead_zone(s.x, self.zone),
                    v=dead_zone(s.y, self.zone), d=dead_zone(s.z, self.zone))


class ReportReplay:
    """A stand-in for easyhid's ``HIDDevice`` (what the library reads): ``read`` returns the queued raw reports one
    a call (zero-padded to the size asked, as hidapi's buffer is), then nothing (b"", as a non-blocking read with no
    report waiting). For tests and demos without a device; ``unplugged = True`` makes the next read fail as easyhid's
    does.

    :param reports: raw HID reports, the report id first (e.g. ``b"\\x03\\x01"``: button 0 down).
    :param vendor_id: the USB vendor id the enumeration shows (default: a SpaceMouse Compact's).
    :param product_id: the USB product id.
    """

    def __init__(self, reports: Iterable[bytes] = (), vendor_id: int = COMPACT[0],
                 product_id: int = COMPACT[1]) -> None:
        self.queue: deque[bytes] = deque(bytes(r) for r in reports)
        self.vendor_id, self.product_id, self.path = vendor_id, product_id, "replay"
        self.product_string, self.manufacturer_string = "SpaceMouse (replayed reports)", "3Dconnexion"
        self.release_number, self.serial_number = 0, ""
        self.opened, self.nonblocking, self.unplugged = False, False, False

    @classmethod
    def from_file(cls, path: str) -> ReportReplay:
        """The reports of a text file: hex bytes, one report a line (spaces allowed), ``#`` starts a comment.

        :param path: the file.
        """
        with open(path, encoding="utf-8") as fh:
            lines = [line.split("#", 1)[0].replace(" ", "").strip() for line in fh]
        return cls(bytes.fromhex(line) for line in lines if line)

    def add(self, *reports: bytes) -> None:
        """Queue more reports (the device sends them)."""
        self.queue.extend(bytes(r) for r in reports)

    def open(self) -> None:
        """easyhid's ``open``."""
        self.opened = True

    def close(self) -> None:
        """easyhid's ``close``."""
        self.opened = False

    def set_nonblocking(self, enable: bool) -> None:
        """easyhid's ``set_nonblocking``."""
        self.nonblocking = bool(enable)

    def read(self, size: int = 64, timeout: int | None = None) -> bytearray:
        """The next report (easyhid's ``read``).

        :param size: the buffer's size (the library asks for its model's report length).
        :param timeout: ignored (nothing waits).
        """
        if self.unplugged:
            from easyhid import HIDException

            raise HIDException("Failed to read from HID device: -1")
        if not self.queue:
            return bytearray()
        return bytearray(self.queue.popleft()[:size]).ljust(size, b"\0")


def _enumerate() -> list:
    """The HID devices connected (easyhid's enumeration, as the library's own ``open``)."""
    try:
        from easyhid import Enumeration

        return list(Enumeration().find())
    except (AttributeError, OSError) as exc:  # easyhid binds hidapi lazily: a missing library fails here
        raise RuntimeError("no SpaceMouse: the hidapi library is not installed (Debian: apt install "
                           "libhidapi-hidraw0)") from exc


def open_spacemouse(name: str | None = None, hid_devices: Sequence | None = None):
    """The first connected supported SpaceMouse (of model ``name`` if given), opened non-blocking, as the library's
    ``SpaceMouseDevice`` in Z-up axes; :class:`RuntimeError` (one line) when there is none.

    :param name: a model name of the library's table (e.g. ``SpaceMouseCompact``); None: any.
    :param hid_devices: the HID devices to choose from (objects like easyhid's ``HIDDevice``: tests give
        :class:`ReportReplay`); None: those connected.
    """
    try:
        from pyspacemouse import AxisConvention, SpaceMouseDevice, apply_axis_convention, get_device_specs
    except ImportError:
        raise RuntimeError(NO_LIBRARY) from None
    specs = get_device_specs()
    if name is not None and name not in specs:
        raise RuntimeError(f"no SpaceMouse model {name!r} (known: {', '.join(specs)})")
    devices = _enumerate() if hid_devices is None else list(hid_devices)
    found = [(n, spec, dev) for dev in devices for n, spec in specs.items()
             if (dev.vendor_id, dev.product_id) == (spec.vendor_id, spec.product_id) and name in (None, n)]
    if not found:
        raise RuntimeError(f"no SpaceMouse: none of the {len(devices)} HID devices here is a supported "
                           f"{name or '3Dconnexion device'} (connect one, or use `khgrl human gamepad`)")
    model, spec, dev = found[0]
    mouse = SpaceMouseDevice(apply_axis_convention(spec, AxisConvention.HID_Z_UP), dev)
    try:
        mouse.open()
    except RuntimeError:
        raise RuntimeError(f"no SpaceMouse: cannot open the {model} at {dev.path} (no read access to it? "
                           "a udev rule may be needed)") from None
    dev.set_nonblocking(True)
    return mouse


def _fraction(text: str) -> float:
    """argparse type: a number in [0, 1)."""
    value = float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1), not {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The SpaceMouse's flags (those of :func:`khgrl.human_bridge.keyboard.add_arguments` and its own)."""
    keyboard.add_arguments(parser, default_id="spacemouse")
    parser.add_argument("--device", default=None, help="the SpaceMouse model, by pyspacemouse's name, e.g. "
                                                       "SpaceMouseCompact (default: the first one found)")
    parser.add_argument("--hold-button", type=int, default=HOLD_BUTTON,
                        help="the button that holds the robot while down (default: %(default)s, the left one)")
    parser.add_argument("--toggle-button", type=int, default=TOGGLE_BUTTON,
                        help="the button that toggles a hold, -1 for none (default: %(default)s, the right one)")
    parser.add_argument("--dead-zone", type=_fraction, default=DEAD_ZONE,
                        help="no push below this fraction of full deflection (default: %(default)s)")


def run(args: argparse.Namespace, proc: ProcessConfig) -> int:
    """``khgrl human spacemouse``: exit 0 when the window is closed (or the run stops), 3 without a display or a
    SpaceMouse.

    :param args: the parsed command line (:func:`add_arguments`).
    :param proc: the resolved run settings.
    """
    replay = os.environ.get(REPORTS_ENV)
    if not replay:
        try:  # before the window: a missing device is what a user needs to hear, not the display
            check_spacemouse(args.device)
        except RuntimeError as exc:
            print(f"khgrl human spacemouse: {exc}", file=sys.stderr, flush=True)
            return keyboard.NO_DISPLAY_EXIT

    def make() -> SpaceMouseInput:
        try:
            devices = [ReportReplay.from_file(replay)] if replay else None
        except (OSError, ValueError) as exc:
            raise RuntimeError(f"{REPORTS_ENV}={replay}: {exc}") from None
        mouse = open_spacemouse(args.device, devices)
        return SpaceMouseInput(mouse, args.hold_button, args.toggle_button, args.dead_zone)

    return keyboard.run_pad(args, proc, "spacemouse", make)
