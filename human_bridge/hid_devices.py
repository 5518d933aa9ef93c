"""Whether a SpaceMouse is plugged in, from the kernel's list of HID devices: no hidapi, no window, no process.

``khgrl up --human spacemouse`` asks before it starts anything and ``khgrl human spacemouse`` before it opens its
window, so a missing device is one line saying so ("no SpaceMouse found"), not a failure 36 s later or a complaint
about the display or the hidapi library. Linux lists each HID device in ``/sys/bus/hid/devices`` as
``BUS:VENDOR:PRODUCT.N`` (hex); where that list cannot be read (another OS), nothing is checked here and opening
the device says what is wrong.
"""

from __future__ import annotations

import os

__all__ = ["HID_DEVICES_ENV", "REPORTS_ENV", "connected_spacemice", "check_spacemouse", "check_human_device"]

REPORTS_ENV = "KHGRL_SPACEMOUSE_REPORTS"  # recorded HID reports a client plays instead of a device (tests, demos)
HID_DEVICES_ENV = "KHGRL_HID_DEVICES"  # where the kernel lists HID devices (default /sys/bus/hid/devices)
_SYSFS = "/sys/bus/hid/devices"


def _ids(root: str) -> set[tuple[int, int]] | None:
    try:
        names = os.listdir(root)
    except OSError:
        return None
    ids = set()
    for name in names:
        parts = name.split(".")[0].split(":")
        if len(parts) == 3:
            try:
                ids.add((int(parts[1], 16), int(parts[2], 16)))
            except ValueError:
                continue
    return ids


def connected_spacemice(root: str | None = None) -> list[str] | None:
    """The models (pyspacemouse's names) of the supported SpaceMice the kernel lists; None where it lists nothing
    readable.

    :param root: the kernel's HID device list (default: ``$KHGRL_HID_DEVICES`` or ``/sys/bus/hid/devices``)
    :raises RuntimeError: pyspacemouse is not installed
    """
    try:
        from pyspacemouse import get_device_specs
    except ImportError:
        raise RuntimeError("no SpaceMouse: pyspacemouse is not installed (pip install 'khgrl[spacemouse]')") from None
    ids = _ids(root or os.environ.get(HID_DEVICES_ENV, _SYSFS))
    if ids is None:
        return None
    return [model for model, spec in get_device_specs().items() if (spec.vendor_id, spec.product_id) in ids]


def check_spacemouse(model: str | None = None, root: str | None = None) -> None:
    """Raise when the kernel lists no supported SpaceMouse (of ``model`` if given).

    :param model: a pyspacemouse model name; None: any
    :param root: see :func:`connected_spacemice`
    :raises RuntimeError: "no SpaceMouse found ..." (one line), or pyspacemouse is missing
    """
    found = connected_spacemice(root)
    if found is not None and not any(model in (None, m) for m in found):
        raise RuntimeError(f"no SpaceMouse found: no {model or 'supported 3Dconnexion device'} is plugged in "
                           f"(the kernel lists none); connect one, or use --human gamepad / keyboard")


def check_human_device(human: str) -> None:
    """``khgrl up``'s check of the run's human-input device, before any process starts.

    :param human: the run's ``--human``
    :raises ValueError: ``spacemouse`` without a SpaceMouse plugged in (and no recorded reports to play)
    """
    if human == "spacemouse" and not os.environ.get(REPORTS_ENV):
        try:
            check_spacemouse()
        except RuntimeError as exc:
            raise ValueError(str(exc)) from None
