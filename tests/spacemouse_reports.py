"""Synthetic raw HID reports as a 3Dconnexion SpaceMouse sends them, for the tests of ``khgrl human spacemouse``
(tests/unit/test_spacemouse.py, tests/integration/test_spacemouse_client.py).

Layouts (pyspacemouse 2.1.0's devices.toml; raw HID axes: +x right, +y toward the user, +z down; signed 16-bit
little-endian): the Compact (and the SpaceNavigator) sends report 1 = x, y, z, report 2 = rx, ry, rz and report 3
= buttons (byte 1: bit 0 left, bit 1 right); the Wireless sends x, y, z, rx, ry, rz in one 13-byte report 1 and
its buttons in report 3.
"""

from __future__ import annotations

import struct

__all__ = ["FULL", "WIRELESS", "USB_NO_BUTTONS", "translation", "rotation", "buttons"]

FULL = 350  # the library's axis_scale: a raw count of 350 is a deflection of 1.0
WIRELESS = (0x256F, 0xC62E)  # SpaceMouseWireless in the library's table: one 13-byte report 1
USB_NO_BUTTONS = (0x256F, 0xC641)  # SpaceMouseUSB: no buttons


def translation(x: int, y: int, z: int) -> bytes:
    """Report 1 of a Compact: raw HID x, y, z (+y toward the user, +z down)."""
    return b"\x01" + struct.pack("<hhh", x, y, z)


def rotation(rx: int, ry: int, rz: int) -> bytes:
    """Report 2 of a Compact: raw HID rx, ry, rz."""
    return b"\x02" + struct.pack("<hhh", rx, ry, rz)


def buttons(left: bool = False, right: bool = False) -> bytes:
    """Report 3: the buttons' bits in byte 1."""
    return bytes([3, int(left) | int(right) << 1])
