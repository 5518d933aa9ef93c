"""``khgrl human keyboard`` and ``khgrl human gamepad``: human input without a mouse.

Unit level: synthetic pygame events (keys; joystick axis and button events posted to pygame's queue) turn into
pushes, and a :class:`~khgrl.human_bridge.keyboard.PadClient` on a stand-in link sends the held P_h. Process level: no
display, or no controller, is exit code 3 with one line; the flags parse. Integration: a client in this process,
connected to a real router + learner + actor of a 3-D task, fetches the task over the wire, is driven by posted
events, and the actor's ``corrections.csv`` records the held P_h moving in the pushed direction, then the
release (``summary.json``: one hold, one release; the last word on the wire is ``active=False``).
"""

from __future__ import annotations

import csv
import os
import subprocess
import time

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from khgrl.common.wire.messages import Correction, Frame  # noqa: E402
from khgrl.common.wire.protocol import decode  # noqa: E402
from khgrl.human_bridge.gamepad import GamepadInput  # noqa: E402
from khgrl.human_bridge.keyboard import WINDOW, KeyboardInput, PadClient  # noqa: E402
from khgrl.human_bridge.velocity import Push  # noqa: E402

from helpers import REPO, FakeLink, ProcGroup, python_main, read_json, unique_run, wait_for  # noqa: E402

OWN = "khgrl.deploy.examples.own_task:make_task"  # a 3-D task (O = 3, view axes x/y, third z), 200 steps an episode
OWN_LOW, OWN_HIGH = np.array([0.02, 0.02, 0.02]), np.array([0.98, 0.98, 0.8])


@pytest.fixture
def display():
    pygame.display.init()
    pygame.font.init()
    yield pygame.display.set_mode(WINDOW)
    pygame.display.quit()


def _ev(kind, **kw):
    return pygame.event.Event(kind, **kw)


def _key(kind, key):
    return _ev(kind, key=key, mod=0, unicode="", scancode=0)


def _env(**over) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")}
    env.update(PYTHONPATH=str(REPO), **over)
    return env


# ------------------------------------------------------------------------------------------ unit level
def test_keys_make_pushes():
    k = KeyboardInput()
    assert k.push() == Push()
    for key in (pygame.K_SPACE, pygame.K_UP, pygame.K_LEFT, pygame.K_PAGEUP):
        assert k.handle(_key(pygame.KEYDOWN, key)) is False
    assert k.push() == Push(hold=True, h=-1.0, v=1.0, d=1.0)
    k.handle(_key(pygame.KEYDOWN, pygame.K_RIGHT))  # left and right together: no push
    k.handle(_key(pygame.KEYUP, pygame.K_UP))
    k.handle(_key(pygame.KEYUP, pygame.K_PAGEUP))
    k.handle(_key(pygame.KEYDOWN, pygame.K_s))  # S: the third axis down (as PageDown)
    assert k.push() == Push(hold=True, h=0.0, v=0.0, d=-1.0)
    k.handle(_key(pygame.KEYUP, pygame.K_SPACE))
    assert not k.push().hold
    k.handle(_key(pygame.KEYDOWN, pygame.K_RETURN))  # Enter toggles a hold
    assert k.push().hold
    k.handle(_ev(pygame.WINDOWFOCUSLOST))  # the key-ups will not come: forget everything
    assert k.push() == Push()
    k.handle(_key(pygame.KEYDOWN, pygame.K_RETURN))
    k.handle(_key(pygame.KEYDOWN, pygame.K_RETURN))
    assert not k.push().hold
    assert k.handle(_key(pygame.KEYDOWN, pygame.K_q)) and k.handle(_key(pygame.KEYDOWN, pygame.K_ESCAPE))
    assert k.handle(_ev(pygame.QUIT))


def test_joystick_events_posted_to_pygame_make_pushes(display):
    g = GamepadInput()

    def feed(*events):
        for e in events:
            pygame.event.post(e)
        for e in pygame.event.get():
            g.handle(e)

    feed(_ev(pygame.JOYBUTTONDOWN, joy=0, instance_id=0, button=0),
         _ev(pygame.JOYAXISMOTION, joy=0, instance_id=0, axis=0, value=0.575),
         _ev(pygame.JOYAXISMOTION, joy=0, instance_id=0, axis=1, value=-1.0),
         _ev(pygame.JOYAXISMOTION, joy=0, instance_id=0, axis=3, value=0.1))  # inside the dead zone
    p = g.push()
    assert p.hold and p.h == pytest.approx(0.5) and p.v == 1.0 and p.d == 0.0  # stick up: +
    feed(_ev(pygame.JOYAXISMOTION, joy=0, instance_id=0, axis=3, value=-1.0),
         _ev(pygame.JOYBUTTONDOWN, joy=0, instance_id=0, button=1))
    assert g.push().d == 1.0
    feed(_ev(pygame.JOYBUTTONUP, joy=0, instance_id=0, button=0))
    assert not g.push().hold  # only button 0 holds
    feed(_ev(pygame.JOYBUTTONDOWN, joy=0, instance_id=0, button=0), _ev(pygame.JOYDEVICEREMOVED, instance_id=0))
    assert g.push() == Push()  # unplugged: released
    other = GamepadInput(hold_button=2, third_axis=4)
    other.handle(_ev(pygame.JOYBUTTONDOWN, joy=0, instance_id=0, button=2))
    other.handle(_ev(pygame.JOYAXISMOTION, joy=0, instance_id=0, axis=4, value=1.0))
    assert other.push() == Push(hold=True, d=-1.0)
    assert g.handle(_key(pygame.KEYDOWN, pygame.K_q)) and g.handle(_ev(pygame.QUIT))


def test_pad_client_sends_the_held_p_h_and_draws_its_state(display):
    from khgrl.human_bridge.gui.task import local_descriptor

    task = local_descriptor("passage:low_cov")  # 2-D: the third push moves nothing
    link, events = FakeLink("kb"), []
    c = PadClient(link, KeyboardInput(), actor="a0", speed=0.5, run="r", task=task,
                  events=lambda: [events.pop(0) for _ in range(len(events))])
    c.step()
    assert "waiting for its frames" in c.lines()[1]
    start = np.array([0.3, 0.5])
    link.queue.append(Frame(actor="a0", episode=1, t=3, phase=0.0, robot=start, desired=start, mean=start,
                            scale=np.ones(2), intervening=False, task=task.name))
    events += [_key(pygame.KEYDOWN, pygame.K_SPACE)]
    c.step()
    assert c.hold.holding and link.pub.sent[-1][2:] == (1, 3)
    np.testing.assert_allclose(link.pub.sent[-1][1], start)
    events += [_key(pygame.KEYDOWN, pygame.K_UP), _key(pygame.KEYDOWN, pygame.K_w)]
    c.step()
    time.sleep(0.1)
    c.step()
    assert c.hold.p_h[0] == start[0] and c.hold.p_h[1] > start[1] + 0.04  # 0.5 units/s up
    c.draw(display)
    assert c.lines()[2].startswith("HOLDING") and c.lines()[3].startswith("P_h  x 0.300  y 0.5")
    events += [_key(pygame.KEYUP, pygame.K_SPACE)]
    c.step()
    assert not c.hold.holding and link.pub.sent[-1][1] is None
    c.draw(display)
    assert c.lines()[2].startswith("free")
    events += [_key(pygame.KEYDOWN, pygame.K_x), _key(pygame.KEYDOWN, pygame.K_r)]
    c.step()  # the e-stop, then ready: both to the actors on the client's own request key
    assert link.commands == ["estop", "ready"] and "E-STOP pressed" in c.lines()[2]
    events += [_key(pygame.KEYDOWN, pygame.K_RETURN), _key(pygame.KEYDOWN, pygame.K_ESCAPE)]
    c.step()  # a toggled hold, then quit: released on the way out
    assert c.quit and not c.hold.holding and link.pub.sent[-1][1] is None
    pad = GamepadInput(estop_button=3)
    c = PadClient(link, pad, actor="a0", speed=0.5, run="r", task=task, events=lambda: [events.pop(0)
                                                                                        for _ in range(len(events))])
    events += [_ev(pygame.JOYBUTTONDOWN, joy=0, instance_id=0, button=3)]
    c.step()
    assert link.commands == ["estop", "ready", "estop"]  # the gamepad's e-stop button


# ------------------------------------------------------------------------------------------ the process
def test_without_a_display_or_a_controller_the_clients_exit_3_with_one_line():
    base = python_main("khgrl.human_bridge.main")
    for name in ("keyboard", "gamepad"):
        p = subprocess.run(base + [name, "--run", "r", "--connect", "tcp/127.0.0.1:1"], cwd=REPO, env=_env(),
                           capture_output=True, text=True, timeout=60)
        lines = p.stderr.strip().splitlines()
        assert p.returncode == 3 and len(lines) == 1 and "no display" in lines[0], (name, p.stdout + p.stderr)
    pygame.joystick.init()
    if pygame.joystick.get_count():
        pytest.skip("a game controller is connected here")
    p = subprocess.run(base + ["gamepad", "--run", "r", "--connect", "tcp/127.0.0.1:1"], cwd=REPO,
                       env=_env(SDL_VIDEODRIVER="dummy"), capture_output=True, text=True, timeout=60)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 3 and len(lines) == 1 and "no joystick" in lines[0], p.stdout + p.stderr


def test_the_flags_parse():
    from khgrl.human_bridge.main import build_parser

    a = build_parser().parse_args(["keyboard", "--run", "r", "--task", OWN, "--speed", "0.05"])
    assert (a.client, a.actor, a.id, a.speed) == ("keyboard", "a0", "keyboard", 0.05)
    a = build_parser().parse_args(["gamepad", "--run", "r", "--actor", "a1", "--third-axis", "4"])
    assert (a.client, a.actor, a.id, a.speed, a.hold_button, a.third_axis) == ("gamepad", "a1", "gamepad", None, 0, 4)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["keyboard", "--run", "r", "--speed", "-1"])


# ---------------------------------------------------------------------------------- real router + actor
def _drive_real_actor(tmp_path, display, client_id: str, device, script) -> tuple[list, list[dict], dict, Frame]:
    """Start a router, a learner and an actor of the 3-D task (2 episodes of 200 steps at 50 Hz, random actions);
    connect a :class:`PadClient` with ``device`` (events from pygame's queue) that fetches the task over the
    wire; at a frame early in an episode run ``script(tick)`` (posting events, calling ``tick``); wait for the
    actor's end. Returns the client's words on the wire, its rows of corrections.csv, the actor's summary and
    the frame the hold started at."""
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.process import StopFlag
    from khgrl.common.wire.protocol import Keys
    from khgrl.human_bridge.client import HumanClient

    run, run_dir = unique_run(client_id[:3]), tmp_path / "run"
    wire: list[Correction] = []
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "100000", run_dir=run_dir)
        with open_client(ep) as session:
            keys = Keys(run)
            spy = session.declare_subscriber(keys.correction("*"), lambda s: wire.append(
                decode(Correction, s.payload.to_bytes())))
            client = PadClient(HumanClient(session, keys, client_id, StopFlag(), "a0", ("frame",)), device,
                               actor="a0", name=client_id, run=run)
            actor = g.actor(run, ep, "--task", OWN, "--method", "khgrl", "--episodes", "2", "--rate", "50",
                            "--learning-starts", "100000", "--max-lead", "100000", run_dir=run_dir)

            def tick(*events):
                for e in events:
                    pygame.event.post(e)
                client.step()
                client.draw(display)
                pygame.display.flip()

            def early():
                tick()
                f = client.frame
                return client.task is not None and f is not None and 10 <= f.t <= 60

            try:
                wait_for(early, 120, "the task and a frame early in an episode", interval=0.01,
                         procs=[actor, learner])
                assert client.task.name == "point-3d" and client.task.out_dim == 3
                start = client.frame
                script(tick)
                assert not client.hold.holding
            finally:
                spy.undeclare()
                client.link.close()
        assert actor.wait(120) == 0, actor.tail()
        learner.stop(30)
    with open(run_dir / "actor-a0" / "corrections.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["client"] == client_id]
    return [m for m in wire if m.client == client_id], rows, read_json(run_dir / "actor-a0" / "summary.json"), start


def _hold_for(tick, seconds: float, *events) -> None:
    tick(*events)
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        tick()
        time.sleep(0.02)


def _check_moved(wire: list, rows: list[dict], summary: dict, up: tuple[int, ...], still: tuple[int, ...]) -> None:
    """One hold, then one release; P_h recorded by the actor moved up along ``up`` and not along ``still``."""
    assert summary["corrections"]["holds"] == 1 and summary["corrections"]["releases"] == 1, summary["corrections"]
    active = [m for m in wire if m.active]
    assert len(active) >= 20 and wire[-1].active is False and all(m.actor == "a0" for m in wire)
    assert len(rows) >= 20, len(rows)
    p = np.array([[float(r[f"p_h_{c}"]) for c in "xyz"] for r in rows])
    steps = [int(r["step"]) for r in rows]
    assert steps == list(range(steps[0], steps[0] + len(steps))), steps  # one run of held steps, then released
    assert len({int(r["episode"]) for r in rows}) == 1
    assert np.all(p >= OWN_LOW) and np.all(p <= OWN_HIGH)
    for k in up:
        assert np.all(np.diff(p[:, k]) >= 0) and p[-1, k] - p[0, k] > 0.03, p[:, k]  # ~0.1 span/s for ~1 s
    for k in still:
        assert np.all(p[:, k] == p[0, k]), p[:, k]


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_keyboard_moves_the_held_p_h_of_a_real_actor(tmp_path, display):
    def script(tick):
        _hold_for(tick, 0.1, _key(pygame.KEYDOWN, pygame.K_SPACE))
        _hold_for(tick, 1.0, _key(pygame.KEYDOWN, pygame.K_UP), _key(pygame.KEYDOWN, pygame.K_PAGEUP))
        tick(_key(pygame.KEYUP, pygame.K_UP), _key(pygame.KEYUP, pygame.K_PAGEUP))
        tick(_key(pygame.KEYUP, pygame.K_SPACE))

    wire, rows, summary, start = _drive_real_actor(tmp_path, display, "keyboard", KeyboardInput(), script)
    _check_moved(wire, rows, summary, up=(1, 2), still=(0,))  # up: y; PageUp: z; x stays
    np.testing.assert_allclose(wire[0].p_h, np.clip(wire[0].p_h, OWN_LOW, OWN_HIGH))
    assert wire[0].episode == start.episode and wire[0].t >= start.t


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_gamepad_moves_the_held_p_h_of_a_real_actor(tmp_path, display):
    def axis(k, v):
        return _ev(pygame.JOYAXISMOTION, joy=0, instance_id=0, axis=k, value=v)

    def script(tick):
        _hold_for(tick, 0.1, _ev(pygame.JOYBUTTONDOWN, joy=0, instance_id=0, button=0))
        _hold_for(tick, 1.0, axis(0, 1.0), axis(1, 0.1), axis(3, -1.0))  # right; y in the dead zone; z up
        tick(axis(0, 0.0), axis(1, 0.0), axis(3, 0.0))
        tick(_ev(pygame.JOYBUTTONUP, joy=0, instance_id=0, button=0))

    wire, rows, summary, start = _drive_real_actor(tmp_path, display, "gamepad", GamepadInput(), script)
    _check_moved(wire, rows, summary, up=(0, 2), still=(1,))
