"""``khgrl human CLIENT``: the human-input process. It hosts one client and talks to actors only through Zenoh
messages (docs/protocol.md): it reads the actors' frames and publishes corrections.

Clients:

* ``scripted`` -- the reproducible stand-in for a person (:mod:`khgrl.human_bridge.scripted`): in the run's
  ``human_episodes`` it asks the task's ``scripted_human`` for P_h (the passage world's holds the desired position
  on a safe path over the scenario's help window). It drives the task the actors run: started by hand without
  ``--task`` it takes the task they announce, or refuses with one line if that task cannot be loaded here.
* ``gui`` -- a pygame window: a person drags the robot with the mouse (:mod:`khgrl.human_bridge.gui`).
* ``replay`` -- feeds a recorded ``corrections.csv`` into a new run at the same episodes and steps
  (:mod:`khgrl.human_bridge.replay`).
* ``keyboard`` / ``gamepad`` -- hold a key / button to intervene and move the desired position with the arrow
  keys / a stick in the task's view axes (:mod:`khgrl.human_bridge.keyboard`, :mod:`khgrl.human_bridge.gamepad`).
* ``spacemouse`` -- the same with a 3Dconnexion SpaceMouse: hold its left button, push the cap in 3-D
  (:mod:`khgrl.human_bridge.spacemouse`; ``khgrl[spacemouse]``).

Started by ``khgrl up`` as ``khgrl human CLIENT --config RUN_DIR/config.json``; by hand (another machine) with
``--run RUN --connect EP`` and any run setting as a flag.
"""

from __future__ import annotations

import argparse
import logging
import sys

from khgrl.common.config.process import ProcessConfig, add_process_flags, resolve_process
from khgrl.common.process import die_with_parent
from khgrl.human_bridge import gamepad, keyboard, replay, scripted, spacemouse
from khgrl.human_bridge.gui import main as gui

__all__ = ["main", "build_parser", "CLIENTS"]

# each client module has add_arguments(parser) and run(args, proc)
CLIENTS = {
    "scripted": (scripted, "the scripted human: reproducible corrections along a safe path"),
    "gui": (gui, "a pygame window: watch an actor and drag its robot with the mouse"),
    "replay": (replay, "feed a recorded corrections.csv into a new run at the same episodes and steps"),
    "keyboard": (keyboard, "a small window: hold Space and move the robot with the arrow keys (no mouse)"),
    "gamepad": (gamepad, "hold button 0 and move the robot with the sticks of a game controller (no mouse)"),
    "spacemouse": (spacemouse, "hold the left button and move the robot in 3-D with a 3Dconnexion SpaceMouse"),
}


def build_parser() -> argparse.ArgumentParser:
    """``khgrl human`` with one sub-command per client: the client's own flags and the run settings."""
    parser = argparse.ArgumentParser(prog="khgrl human", description="Human-input process: hosts one client.")
    sub = parser.add_subparsers(dest="client", required=True, metavar="CLIENT")
    for name, (module, help_text) in CLIENTS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(p)
        add_process_flags(p, "human")  # the settings whose roles name the human clients
    return parser


def _resolve(args: argparse.Namespace) -> ProcessConfig:
    if getattr(args, "offline", False) and not getattr(args, "cfg__run", None):
        args.cfg__run = "offline"  # an offline screenshot (gui) joins no run
    return resolve_process(args)


def main(argv: list[str] | None = None) -> int:
    """Parse and resolve the settings (exit 2 with a one-line error if they are bad), then run the client."""
    die_with_parent()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    args = build_parser().parse_args(argv)
    try:
        proc = _resolve(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"khgrl human {args.client}: {exc}", file=sys.stderr, flush=True)
        return 2
    return int(CLIENTS[args.client][0].run(args, proc) or 0)


if __name__ == "__main__":
    sys.exit(main())
