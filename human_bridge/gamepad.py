"""``khgrl human gamepad``: correct an actor with a game controller (no mouse), for any task.

The same window and hold logic as ``khgrl human keyboard`` (:mod:`khgrl.human_bridge.keyboard`,
:class:`~khgrl.human_bridge.velocity.VelocityHold`); the controller (:class:`GamepadInput`, pygame joystick events):

* **button 0** (``--hold-button``; "A" / "cross" on most pads), held -- hold the robot: P_h starts at its desired
  position and the sticks move it; letting go releases it.
* **left stick** (axes 0 and 1) -- move P_h in the main view: right / left along ``view_axes[0]``, up / down
  along ``view_axes[1]``; the further the stick is pushed, the faster (full push: ``--speed``).
* **right stick vertical** (axis 3, ``--third-axis``) -- up / down along the third axis (``view_third``; z of a
  3-D task such as ``fetch:moved``).
* **button 1** (``--estop-button``; "B" / "circle"), or x in the window -- the e-stop: every actor holds its robot
  until ``khgrl stop RUN_DIR --release``.
* A dead zone of 0.15 (:data:`~khgrl.human_bridge.velocity.DEAD_ZONE`) around the centre is no push. q or Esc in the
  window, or closing it, quits (releasing first); unplugging the controller releases.

Exit code 3 with one line when there is no display or pygame finds no controller (``--joystick`` picks one
when there are several).
"""

from __future__ import annotations

import argparse

from khgrl.common.config.process import ProcessConfig
from khgrl.human_bridge import keyboard
from khgrl.human_bridge.velocity import DEAD_ZONE, Push, dead_zone

__all__ = ["GamepadInput", "open_joystick", "add_arguments", "run", "HOLD_BUTTON", "THIRD_AXIS"]

HOLD_BUTTON = 0
ESTOP_BUTTON = 1  # "B" / "circle": the e-stop (x in the window too)
THIRD_AXIS = 3  # the right stick's vertical axis on most pads (SDL's joystick numbering)


class GamepadInput:
    """A controller's sticks and buttons, as a :class:`~khgrl.human_bridge.velocity.Push` (see the module docstring).

    :param hold_button: the button that holds the robot while down.
    :param third_axis: the axis that moves the third output (up = +).
    :param zone: the sticks' dead zone.
    :param device: the opened pygame joystick (kept open so its events come; None in tests that post events).
    """

    help = "hold button 0 + left stick (main view), right stick up/down (third axis); q: quit"

    def __init__(self, hold_button: int = HOLD_BUTTON, third_axis: int = THIRD_AXIS, zone: float = DEAD_ZONE,
                 device=None, estop_button: int = ESTOP_BUTTON) -> None:
        self.hold_button, self.third_axis, self.zone, self.device = hold_button, third_axis, zone, device
        self.estop_button = estop_button
        self.axes: dict[int, float] = {}
        self.buttons: set[int] = set()

    def handle(self, event) -> bool:
        """Take one pygame event; True asks to quit.

        :param event: a joystick event (axis motion, button down / up, device removed), or a window / key event.
        """
        import pygame

        if keyboard.quit_event(event):
            return True
        if event.type == pygame.JOYAXISMOTION:
            self.axes[int(event.axis)] = float(event.value)
        elif event.type == pygame.JOYBUTTONDOWN:
            self.buttons.add(int(event.button))
        elif event.type == pygame.JOYBUTTONUP:
            self.buttons.discard(int(event.button))
        elif event.type == getattr(pygame, "JOYDEVICEREMOVED", -1):
            self.clear()
        return False

    def estop(self, event) -> bool:
        """Whether ``event`` presses the e-stop button.

        :param event: a pygame event.
        """
        import pygame

        return event.type == pygame.JOYBUTTONDOWN and int(event.button) == self.estop_button

    def clear(self) -> None:
        """Forget the sticks and buttons (the controller went away)."""
        self.axes.clear()
        self.buttons.clear()

    def push(self) -> Push:
        """The controller's state now (stick up is negative on SDL's axes: up pushes +)."""
        def axis(k: int) -> float:
            return dead_zone(self.axes.get(k, 0.0), self.zone)

        return Push(hold=self.hold_button in self.buttons, h=axis(0), v=-axis(1), d=-axis(self.third_axis))


def open_joystick(index: int = 0):
    """The opened pygame joystick ``index``; :class:`RuntimeError` (one line) when there is none.

    :param index: which controller, when there are several.
    """
    import pygame

    pygame.joystick.init()
    count = pygame.joystick.get_count()
    if count == 0:
        raise RuntimeError("no joystick: pygame finds no game controller (connect one, or use "
                           "`khgrl human keyboard`)")
    if not 0 <= index < count:
        raise RuntimeError(f"no joystick {index}: pygame finds {count} (0..{count - 1})")
    js = pygame.joystick.Joystick(index)
    js.init()
    return js


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The gamepad's flags (those of :func:`khgrl.human_bridge.keyboard.add_arguments` and its own)."""
    keyboard.add_arguments(parser, default_id="gamepad")
    parser.add_argument("--joystick", type=int, default=0, help="which controller (default: %(default)s)")
    parser.add_argument("--hold-button", type=int, default=HOLD_BUTTON,
                        help="the button that holds the robot while down (default: %(default)s)")
    parser.add_argument("--estop-button", type=int, default=ESTOP_BUTTON,
                        help="the button that presses the e-stop (default: %(default)s)")
    parser.add_argument("--third-axis", type=int, default=THIRD_AXIS,
                        help="the stick axis that moves the third output (default: %(default)s, the right "
                             "stick's vertical)")


def run(args: argparse.Namespace, proc: ProcessConfig) -> int:
    """``khgrl human gamepad``: exit 0 when the window is closed (or the run stops), 3 without a display or a
    controller.

    :param args: the parsed command line (:func:`add_arguments`).
    :param proc: the resolved run settings.
    """
    return keyboard.run_pad(args, proc, "gamepad", lambda: GamepadInput(
        args.hold_button, args.third_axis, device=open_joystick(args.joystick), estop_button=args.estop_button))
