"""``khgrl human gui``: the pygame human-input client.

Unit level: typed frames and synthetic pygame events drive :class:`khgrl.human_bridge.gui.app.GuiApp` (no Zenoh), and
:class:`khgrl.human_bridge.gui.view.GuiView` draws it, for the passage world (2-D, one view) and a 3-D task (two views:
a drag in either sets that view's two coordinates). Process level: the real ``khgrl human gui`` process fails loudly
without a display, writes offline screenshots, and runs its window (``SDL_VIDEODRIVER=dummy``) against a router
until stopped. Integration: a GUI in this process, connected to a real router + learner + actor, receives the
actor's frames; synthetic mouse events (``pygame.event.post``) produce real correction messages on the wire, and
the actor stores intervened transitions (episodes.csv, corrections.csv, the learner's checkpoint).
"""

from __future__ import annotations

import csv
import functools
import os
import subprocess
import time
from pathlib import Path

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from khgrl.common.wire.messages import ActorInfo, LearnerInfo  # noqa: E402
from khgrl.common.wire.protocol import Correction, Frame, RejectCounter, Scale, Status, TaskInfo, decode, encode  # noqa: E402
from khgrl.human_bridge.gui.app import GuiApp  # noqa: E402
from khgrl.human_bridge.gui.view import GuiView  # noqa: E402

from helpers import REPO, ProcGroup, python_main, read_json, unique_run, wait_for  # noqa: E402


@functools.lru_cache(maxsize=None)
def _task(spec: str = "passage:low_cov"):
    """The descriptor an actor of ``spec`` announces (built here once)."""
    from khgrl.human_bridge.gui.task import local_descriptor

    return local_descriptor(spec)


class _Point3:
    """A 3-D point robot that goes where it is told (a minimal task environment)."""

    @staticmethod
    def env(seed: int = 0):
        import gymnasium as gym

        class Point3(gym.Env):
            observation_space = gym.spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float64)
            action_space = gym.spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float64)

            def reset(self, *, seed=None, options=None):
                super().reset(seed=seed)
                self.p = np.array([0.1, 0.5, 0.2])
                return self.p.copy(), {}

            def step(self, action):
                self.p = np.clip(np.asarray(action, np.float64), 0.0, 1.0)
                return self.p.copy(), 0.0, False, False, {}

        return Point3()

    @staticmethod
    def task():
        """Demonstrations from (0.1, 0.5, 0.2) to (0.9, 0.5, 0.2) over a box, fanning in y and lifting in z."""
        from khgrl.common.tasks.api import Cuboid, Point, Task, View

        s = np.linspace(0.0, 1.0, 60)
        demos = np.stack([np.c_[0.1 + 0.8 * s, 0.5 + dy * np.sin(np.pi * s), 0.2 + dz * np.sin(np.pi * s)]
                          for dy, dz in ((-0.2, 0.5), (-0.1, 0.6), (0.1, 0.55), (0.2, 0.45))])
        view = View(axes=(0, 1), third=2, names=("x", "y", "z"),
                    shapes=(Cuboid("keep-out", (0.4, 0.4, 0.0), (0.6, 0.6, 0.4)), Point("start", (0.1, 0.5, 0.2)),
                            Point("goal", (0.9, 0.5, 0.2))))
        return Task(name="point3", make_env=_Point3.env, demos=demos, workspace=((0, 0, 0), (1, 1, 1)),
                    default_scale=0.5, position=lambda obs: obs, view=view)


@functools.lru_cache(maxsize=None)
def _task3():
    from khgrl.common.tasks.world import build_task_world
    from khgrl.human_bridge.gui.task import local_descriptor

    return local_descriptor("tests.point3:task", world=build_task_world(_Point3.task()))


def _frame(actor="a0", episode=1, t=5, task="passage-low_cov", intervening=False, scale=15.0,
           at=(0.1, 0.5), **kw) -> Frame:
    """A frame as it comes off the wire (encoded and decoded)."""
    at = np.asarray(at, dtype=np.float64)
    f = Frame(actor=actor, episode=episode, t=t, phase=t / 399, robot=at, desired=at, mean=at,
              scale=np.broadcast_to(np.asarray(scale, np.float64), at.shape).copy(), intervening=intervening, task=task,
              ret=-1.5, **kw)
    return decode(Frame, encode(f, actor, t))


def _actor_status(actor="a0", paused=False) -> Status:
    info = ActorInfo(id=actor, episode=1, t=5, transitions=5, sent=0, next_seq=0, outbox=0, received=-1, durable=-1,
                     trained=0, weights_version=0, ack_version=0, learner_alive=False, waits=0, wait_s=0.0, resends=0,
                     corrections={}, intervening=False, rejects={}, paused=paused, period_ms_p50=None)
    return decode(Status, encode(Status(role="actor", info=info), actor, 1))


class Sink:
    def __init__(self):
        self.sent: list[tuple] = []
        self.controls: list[str] = []

    def send(self, actor, p_h, episode, t):
        self.sent.append((actor, None if p_h is None else np.asarray(p_h).copy(), episode, t))

    def control(self, command):
        self.controls.append(command)


@pytest.fixture
def display():
    pygame.display.init()
    pygame.font.init()
    yield pygame.display.set_mode((600, 770))
    pygame.display.quit()


def _post_and_handle(app, *events):
    for e in events:
        pygame.event.post(e)
    for e in pygame.event.get():
        app.handle(e)


def _ev(kind, **kw):
    return pygame.event.Event(kind, **kw)


def _env(**over) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")}
    env.update(PYTHONPATH=str(REPO), **over)
    return env


# ------------------------------------------------------------------------------------------ unit level
def test_drag_sends_pointer_position_each_frame_and_release(display):
    sink = Sink()
    app = GuiApp(sink.send, sink.control, size=600, task=_task())
    view = GuiView(app)
    app.offer(_frame(t=5))
    assert app.current == "a0" and app.actors["a0"].frame.t == 5
    assert (app.width, app.height) == (600, 770) and len(app.layout.views) == 1
    view.draw(display)
    ref = app.layout
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(300, 150), button=1))
    assert app.dragging
    a, p, ep, t = sink.sent[-1]
    assert (a, ep, t) == ("a0", 1, 5)
    np.testing.assert_allclose(p, ref.to_world(0, (300, 150)))
    np.testing.assert_allclose(ref.to_pixel(0, p), (300, 150), atol=1e-6)  # the pointer's point, where it is drawn
    assert 0.0 < p[0] < 1.0 and 0.5 < p[1] < 1.0  # right of the left edge, above the middle of the passage world
    _post_and_handle(app, _ev(pygame.MOUSEMOTION, pos=(320, 100), rel=(20, -50), buttons=(1, 0, 0)))
    n = len(sink.sent)
    app.offer(_frame(t=6))
    app.offer(_frame(t=7))
    assert len(sink.sent) == n + 2  # one active correction per frame while held
    np.testing.assert_allclose(sink.sent[-1][1], ref.to_world(0, (320, 100)))
    assert sink.sent[-1][2:] == (1, 7)
    app.last_send -= 1.0  # keepalive while no frame arrives
    app.keepalive()
    assert len(sink.sent) == n + 3 and sink.sent[-1][1] is not None
    view.draw(display)  # the drag is drawn (correction cross, HUMAN badge)
    assert any(line.startswith("YOU DRAG") for line in view.text(app.driven))
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONUP, pos=(320, 100), button=1))
    assert not app.dragging and sink.sent[-1][1] is None
    n = len(sink.sent)
    app.offer(_frame(t=8))
    app.keepalive()
    assert len(sink.sent) == n  # released: nothing more
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(300, 650), button=1))  # the strip is not a view
    assert not app.dragging and len(sink.sent) == n


def test_a_3d_task_is_corrected_from_its_two_views(display):
    """Two views side by side: a drag in the (x, z) view sets x and z and keeps y where the desired position is;
    one in the (x, y) view sets x and y. Frames and tables of another size are refused; the window is drawn."""
    d = _task3()
    sink = Sink()
    rejects = RejectCounter("test")
    app = GuiApp(sink.send, sink.control, task=d, size=300, rejects=rejects)
    view = GuiView(app)
    lay = app.layout
    assert (app.width, app.height) == (600, 300 + 80 + 90) and [v.axes for v in lay.views] == [(0, 1), (0, 2)]
    app.offer(_frame(t=5, task="point3", at=(0.2, 0.3, 0.4)))
    px = lay.to_pixel(1, np.array([0.5, 0.0, 0.8]))
    assert lay.view_at(px) == 1
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=tuple(px), button=1))
    np.testing.assert_allclose(sink.sent[-1][1], [0.5, 0.3, 0.8], atol=0.01)
    assert sink.sent[-1][1][1] == 0.3  # y: the desired position's, not the pointer's
    px2 = lay.to_pixel(1, np.array([0.6, 0.0, 0.7]))
    _post_and_handle(app, _ev(pygame.MOUSEMOTION, pos=tuple(px2), rel=(1, 1), buttons=(1, 0, 0)))
    app.offer(_frame(t=6, task="point3", at=(0.5, 0.3, 0.8)))
    np.testing.assert_allclose(sink.sent[-1][1], [0.6, 0.3, 0.7], atol=0.01)
    view.draw(display)
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONUP, pos=tuple(px2), button=1))
    assert sink.sent[-1][1] is None
    app.offer(_frame(t=7, task="point3", at=(0.6, 0.3, 0.7)))
    px3 = lay.to_pixel(0, np.array([0.7, 0.9, 0.0]))
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=tuple(px3), button=1))
    np.testing.assert_allclose(sink.sent[-1][1], [0.7, 0.9, 0.7], atol=0.01)
    assert sink.sent[-1][1][2] == 0.7
    # what does not fit the task is refused and changes nothing
    app.offer(_frame(t=8, task="passage-low_cov", at=(0.1, 0.5)))
    assert app.actors["a0"].frame.t == 7 and rejects.by_kind() == {"frame": 1}
    n = d.horizon
    app.offer(decode(Scale, encode(Scale(actor="a0", model={}, table=np.ones((n, 2))), "a0", 0)))
    app.offer(decode(Scale, encode(Scale(actor="a0", model={}, table=np.c_[np.linspace(0.2, 1.0, n), np.ones((n, 2))]),
                                   "a0", 1)))
    assert rejects.by_kind() == {"frame": 1, "scale": 1}
    phases, L = view.scale_curve(app.actors["a0"])
    assert L.shape == (n, 3) and L[-1, 0] == 1.0
    band = view.band(app.actors["a0"])
    assert band.shape == (n, 2, 3) and np.all(band[:, 1] >= band[:, 0])
    surf = pygame.Surface((app.width, app.height))
    view.draw(surf)
    img = pygame.surfarray.array3d(surf)
    left, right = img[:300, :380], img[300:, :380]
    assert left.std() > 10 and right.std() > 10 and not np.array_equal(left, right)  # two different views


def test_the_task_comes_over_the_wire_and_sizes_the_window():
    """Frames before the task are kept; a TaskInfo sets the task (and the window's width); another task's
    descriptor is refused."""
    rejects = RejectCounter("test")
    app = GuiApp(Sink().send, size=300, rejects=rejects)
    view = GuiView(app)
    assert "waiting for the run's task" in view.text(None)[0]
    app.press((100, 100))  # nothing to drag in yet
    assert not app.dragging
    app.offer(_frame(t=3, task="point3", at=(0.2, 0.3, 0.4)))
    assert app.width == 300
    app.offer(decode(TaskInfo, encode(TaskInfo(sender_id="a0", descriptor=_task3()), "a0", 0)))
    assert app.task.digest == _task3().digest and (app.width, app.height) == (600, 470)
    assert app.actors["a0"].frame.t == 3
    app.offer(decode(TaskInfo, encode(TaskInfo(sender_id="a1", descriptor=_task()), "a1", 0)))
    assert app.task.digest == _task3().digest and rejects.by_kind() == {"task": 1}
    pygame.font.init()
    surf = pygame.Surface((app.width, app.height))
    view.draw(surf)


def test_synthetic_frames_of_a_3d_task_make_a_screenshot(tmp_path):
    from khgrl.common.tasks.kgrl_env import KGRLEnv
    from khgrl.common.tasks.world import build_task_world
    from khgrl.human_bridge.gui.main import synthetic_frames

    env = KGRLEnv(world=build_task_world(_Point3.task()))
    frames = synthetic_frames(env, steps=40, drag_from=30)
    assert len(frames) == 40 and frames[-1].intervening and not frames[0].intervening
    assert all(len(f.robot) == 3 for f in frames)
    np.testing.assert_allclose(frames[-1].desired[1] - frames[-1].mean[1], 0.08)  # dragged up in the main view
    app = GuiApp(Sink().send, task=_task3(), size=300)
    for f in frames:
        app.offer(f)
    pygame.font.init()
    GuiView(app).save_png(str(tmp_path / "g3.png"))
    assert pygame.image.load(str(tmp_path / "g3.png")).get_size() == (600, 470)


def test_a_live_hold_ends_with_its_episode():
    sink = Sink()
    app = GuiApp(sink.send, sink.control, task=_task())
    app.offer(_frame(episode=3, t=40))
    app.press((300, 150))
    app.offer(_frame(episode=3, t=41))
    assert [s[1] is not None for s in sink.sent] == [True, True]
    app.offer(_frame(episode=3, t=42, last=True))  # the episode's last frame: release, no active word for it
    assert not app.dragging and sink.sent[-1][1] is None and sink.sent[-1][2:] == (3, 42)
    n = len(sink.sent)
    app.move((310, 150))  # the button is still down, but the hold is over
    app.offer(_frame(episode=4, t=0))
    app.last_send -= 1.0
    app.keepalive()
    assert len(sink.sent) == n
    app.offer(_frame("a1", episode=1, t=9, last=True))  # another actor's episode end does not touch our drag
    app.press((300, 150))
    app.offer(_frame("a1", episode=1, t=10, last=True))
    assert app.dragging and sink.sent[-1][0] == "a0"


def test_status_is_read_through_the_typed_actor_info():
    app = GuiApp(Sink().send, task=_task())
    view = GuiView(app)
    app.offer(_frame())
    assert "running" in view.text(app.driven)[1]
    app.offer(_actor_status("a0", paused=True))
    assert isinstance(app.actors["a0"].status, ActorInfo) and app.actors["a0"].status.paused
    assert "PAUSED" in view.text(app.driven)[1]
    learner = LearnerInfo(id="learner", epoch="e", ingested=0, iterations=0, gradient_steps=0, grad_steps_per_s=0.0,
                          version=0, pending_iterations=0, queue_depth=0, rejects={}, paused=False, checkpoints=0,
                          next_seq={}, durable={}, duplicates={}, weights_queries=0)
    app.offer(decode(Status, encode(Status(role="learner", info=learner), "learner", 1)))
    app.offer(_actor_status("a9", paused=False))  # an actor it never saw a frame of
    assert app.actors["a0"].status.paused and set(app.actors) == {"a0"}


def test_keys_pause_overlays_tab_quit(display):
    sink = Sink()
    app = GuiApp(sink.send, sink.control, task=_task())
    view = GuiView(app)
    app.offer(_frame("a0"))
    app.offer(_frame("a1", at=(0.3, 0.4)))
    assert app.current == "a0"
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_SPACE, mod=0, unicode=" "))
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_SPACE, mod=0, unicode=" "))
    assert sink.controls == ["pause", "resume"]
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_o, mod=0, unicode="o"))
    assert app.overlays is False
    view.draw(display)
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(200, 200), button=1))
    assert app.dragging and sink.sent[-1][0] == "a0"
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_TAB, mod=0, unicode="\t"))
    assert app.current == "a1" and not app.dragging
    assert sink.sent[-1][0] == "a0" and sink.sent[-1][1] is None  # released a0 before switching
    view.draw(display)  # the other actor
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(200, 200), button=1))
    assert sink.sent[-1][0] == "a1" and sink.sent[-1][1] is not None
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_q, mod=0, unicode="q"))
    assert app.quit and not app.dragging and sink.sent[-1] == ("a1", None, 1, 5)
    app2 = GuiApp(sink.send, sink.control)
    _post_and_handle(app2, _ev(pygame.KEYDOWN, key=pygame.K_ESCAPE, mod=0, unicode="\x1b"))
    assert app2.quit


def test_scale_table_drives_curve_and_band_and_bad_input_is_rejected(display):
    from khgrl.common.tasks.passage.env import build_world
    from khgrl.human_bridge.client import read

    app = GuiApp(Sink().send, task=_task())
    view = GuiView(app)
    app.offer(_frame(scale=(15.0, 15.0)))
    v = app.actors["a0"]
    phases, L = view.scale_curve(v)
    assert np.all(L == 15.0)  # flat at the frame's scale without a scale message
    w = build_world("low_cov")
    n = w.model.n_points
    table = np.c_[np.linspace(5, 30, n), np.full(n, 15.0)]
    app.offer(decode(Scale, encode(Scale(actor="a0", model={"default": [15.0, 15.0]}, table=table), "a0", 0)))
    phases, L = view.scale_curve(v)
    np.testing.assert_allclose(L, table)
    band = view.band(v)
    half = np.einsum("nij,nj->ni", np.abs(w.model.grid_projector), table)
    np.testing.assert_allclose(band[:, 1] - band[:, 0], 2 * half)
    view.draw(display)
    # what the wire brings in is decoded by the client (khgrl.human_bridge.client.read) into typed messages
    rejects = RejectCounter("test")
    assert read("frame", "k/a0", b"\xc1garbage", rejects) is None
    nan_ret = encode(_frame(), "a0", 1).replace(b"\xcb\xbf\xf8\x00\x00\x00\x00\x00\x00", b"\xcb\x7f\xf8" + bytes(6))
    assert read("frame", "k/a0", nan_ret, rejects) is None  # ret NaN
    assert read("frame", "k/a0", encode(_frame(), "a0", 1), rejects) is not None
    app2 = GuiApp(Sink().send, rejects=rejects)
    app2.offer(_frame())
    app2.offer(decode(Scale, encode(Scale(actor="a0", model={}, table=-table), "a0", 1)))
    assert rejects.by_kind() == {"frame": 2, "scale": 1}
    app.offer(decode(Scale, encode(Scale(actor="a0", model={}, table=-table), "a0", 1)))
    np.testing.assert_allclose(view.scale_curve(v)[1], table)  # the refused table changed nothing


def test_human_parser_takes_run_settings_and_client_flags(tmp_path):
    from khgrl.common.config.settings import RunConfig, write_run_config
    from khgrl.human_bridge.main import _resolve, build_parser

    a = build_parser().parse_args(["gui", "--run", "r", "--connect", "tcp/127.0.0.1:1", "--scenario", "low_cov",
                                   "--actor", "*", "--seed", "0", "--human-episodes", "2"])
    assert a.client == "gui" and a.actor == "*"
    cfg = write_run_config(tmp_path, RunConfig(scenario="low_cov", seed=3, human_episodes=(2, 5)),
                           {"run": "cfgrun", "endpoint": "tcp/127.0.0.1:9"})
    for client, extra in (("scripted", []), ("replay", ["rec.csv"]), ("gui", [])):
        args = build_parser().parse_args([client, *extra, "--config", str(cfg), "--human-noise", "0.01"])
        proc = _resolve(args)
        assert (proc.run, proc.endpoint) == ("cfgrun", "tcp/127.0.0.1:9")
        assert (proc.cfg.scenario, proc.cfg.seed) == ("low_cov", 3)
        assert proc.cfg.human_episodes == (2, 5) and proc.cfg.human_noise == 0.01
    assert build_parser().parse_args(["scripted", "--run", "r"]).actor == "*"


# ------------------------------------------------------------------------------------------ the process
def test_gui_without_a_display_fails_loudly(tmp_path):
    """No DISPLAY, no WAYLAND_DISPLAY, no SDL_VIDEODRIVER: exit 3 at once (before waiting for the router, which
    is not there) with one line on stderr that names the problem."""
    p = subprocess.run(python_main("khgrl.human_bridge.main") + ["gui", "--run", "r", "--connect", "tcp/127.0.0.1:1"],
                       cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)
    assert p.returncode == 3, p.stdout + p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "no display" in lines[0] and "DISPLAY" in lines[0], p.stderr
    # an explicit driver that cannot open a window: SDL's reason, same exit code
    p = subprocess.run(python_main("khgrl.human_bridge.main") + ["gui", "--run", "r", "--connect", "tcp/127.0.0.1:1"],
                       cwd=REPO, env=_env(SDL_VIDEODRIVER="x11"), capture_output=True, text=True, timeout=60)
    assert p.returncode == 3 and "SDL could not open a window" in p.stderr, p.stdout + p.stderr


def test_screenshot_offline_writes_png(tmp_path):
    out = tmp_path / "gui.png"
    p = subprocess.run(python_main("khgrl.human_bridge.main") + ["gui", "--screenshot", str(out), "--offline",
                                                           "--scenario", "low_cov", "--size", "400"],
                       cwd=REPO, env=_env(), capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    img = pygame.image.load(str(out))
    assert img.get_size() == (400, 400 + 80 + 90)


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_gui_window_process_runs_with_the_dummy_driver_until_stopped(tmp_path):
    """``SDL_VIDEODRIVER=dummy`` set explicitly: the window opens (headless), joins the router, publishes its
    status, and stops cleanly on SIGTERM."""
    from khgrl.common.delivery.transport import Inbox, open_client
    from khgrl.common.wire.protocol import Keys

    run = unique_run("guiw")
    assert os.environ["SDL_VIDEODRIVER"] == "dummy"  # (set at the top of this module; the children inherit it)
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        gui = g.start("gui", python_main("khgrl.human_bridge.main")
                      + ["gui", "--run", run, "--connect", ep, "--fps", "20"])
        inbox = Inbox()
        with open_client(ep) as s:
            sub = s.declare_subscriber(Keys(run).status("human", "gui"), inbox.callback("status"))
            got = wait_for(lambda: inbox.get(0.2), 60, "the GUI's status", procs=[gui])
            sub.undeclare()
        st = decode(Status, got[2])
        assert st.role == "human" and st.info.frames == 0 and st.info.corrections == 0
        assert "drag the robot" in gui.text()
        assert gui.stop(30) == 0, gui.tail()


# ---------------------------------------------------------------------------------- real router + actor
@pytest.mark.integration
@pytest.mark.timeout(240)
def test_gui_mouse_drag_over_real_actor_produces_intervened_transitions(tmp_path, display):
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.process import StopFlag
    from khgrl.common.wire.protocol import Keys
    from khgrl.human_bridge.client import HumanClient
    from khgrl.human_bridge.gui.main import GUI_KINDS, GuiSession

    run = unique_run("gui")
    run_dir = tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "100000", run_dir=run_dir)
        keys = Keys(run)
        wire: list[Correction] = []
        statuses: dict = {}
        with open_client(ep) as session:
            net = GuiSession(HumanClient(session, keys, "gui", StopFlag(), "a0", GUI_KINDS))
            spy = session.declare_subscriber(keys.correction("*"), lambda s: wire.append(
                decode(Correction, s.payload.to_bytes())))
            st = session.declare_subscriber(keys.status("actor", "a0"), lambda s: statuses.update(
                info=decode(Status, s.payload.to_bytes()).info))
            app = net.app(actor="a0", run=run, task=_task())  # built before the actor's (short) episodes run
            view = GuiView(app)
            r = app.layout
            actor = g.actor(run, ep, "--scenario", "low_cov", "--method", "khgrl", "--episodes", "2", "--rate", "50",
                            "--learning-starts", "16", "--max-lead", "100000", run_dir=run_dir)

            def tick(*events):
                net.pump(app)
                _post_and_handle(app, *events)
                app.keepalive()
                view.draw(display)
                pygame.display.flip()

            def at(t_min):
                def ok():
                    tick()
                    v = app.actors.get("a0")
                    return v is not None and v.frame is not None and v.frame.episode == 1 and v.frame.t >= t_min
                return ok

            try:
                wait_for(at(30), 120, "frames of episode 1 from the actor", procs=[actor, learner])
                asked = GuiApp(lambda *a: None)  # a GUI that starts without the task asks the actors for it
                assert net.fetch_task(asked, timeout=5.0) and asked.task.digest == _task().digest
                mean = np.asarray(app.actors["a0"].frame.mean)
                px = r.to_pixel(0, mean + np.array([0.0, 0.05]))
                tick(_ev(pygame.MOUSEBUTTONDOWN, pos=tuple(int(v) for v in px), button=1))
                t0 = time.monotonic()
                k = 0
                while time.monotonic() - t0 < 1.5:
                    k += 1
                    px2 = (int(px[0]) + k, int(px[1]))
                    tick(_ev(pygame.MOUSEMOTION, pos=px2, rel=(1, 0), buttons=(1, 0, 0)))
                    time.sleep(0.02)
                tick(_ev(pygame.MOUSEBUTTONUP, pos=px2, button=1))
                tick(_ev(pygame.KEYDOWN, key=pygame.K_SPACE, mod=0, unicode=" "))  # pause the actor

                def paused():
                    tick()
                    return "info" in statuses and statuses["info"].paused is True
                wait_for(paused, 30, "the actor to report paused", procs=[actor])
                n0 = app.actors["a0"].frames
                t1 = time.monotonic()
                while time.monotonic() - t1 < 0.5:
                    tick()
                    time.sleep(0.02)
                n1 = app.actors["a0"].frames
                assert n1 - n0 <= 1, "frames kept coming while paused"
                tick(_ev(pygame.KEYDOWN, key=pygame.K_SPACE, mod=0, unicode=" "))

                def moving():
                    tick()
                    return app.actors["a0"].frames > n1 + 5
                wait_for(moving, 30, "frames after resume", procs=[actor])
            finally:
                spy.undeclare()
                st.undeclare()
                net.link.close()
        assert actor.wait(120) == 0, actor.tail()
        learner.stop(30)  # the checkpoint the actor asked for at its flush is on disk

    # real corrections were on the wire: active ones with the pointer's P_h, then one release
    mine = [m for m in wire if m.client == "gui"]
    active = [m for m in mine if m.active]
    assert len(active) >= 10, len(active)
    assert mine[-1].active is False
    assert all(m.actor == "a0" for m in mine)
    drag_eps = {m.episode for m in mine}  # a drag may run over the end of a (short, random-policy) episode
    np.testing.assert_allclose(active[0].p_h, r.to_world(0, tuple(int(v) for v in px)))
    # ... and the actor applied them: intervened steps in its episode statistics, its corrections record and the
    # learner's replay buffer
    with open(run_dir / "actor-a0" / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    iv = {int(r["episode"]): int(r["intervention_steps"]) for r in rows if int(r["intervention_steps"])}
    iv_steps = sum(iv.values())
    assert iv_steps >= 20, rows  # ~1.5 s held at 50 Hz
    assert set(iv) <= drag_eps, (iv, drag_eps)
    summary = read_json(run_dir / "actor-a0" / "summary.json")
    assert summary["corrections"]["holds"] == 1 and summary["corrections"]["releases"] == 1, summary["corrections"]
    with open(run_dir / "actor-a0" / "corrections.csv", newline="") as fh:
        rec = list(csv.DictReader(fh))
    assert len(rec) == iv_steps and {r["client"] for r in rec} == {"gui"}
    assert {int(r["episode"]) for r in rec} == set(iv)
    _check_replay_buffer(run_dir, rows, iv_steps)


def _check_replay_buffer(run_dir: Path, rows: list[dict], iv_steps: int) -> None:
    """The learner's checkpoint holds every transition, ``iv_steps`` of them intervened."""
    from khgrl.learner.checkpoint import load_checkpoint_arrays

    arrays = load_checkpoint_arrays(run_dir / "learner" / "checkpoint")
    filled = arrays["provenance_actor"] >= 0
    assert int(filled.sum()) == sum(int(r["steps"]) for r in rows)
    assert int(arrays["intervened"][filled].sum()) == iv_steps
