"""``khgrl human gui``: the pygame human-input client.

Unit level: typed frames and synthetic pygame events drive :class:`human_bridge.gui.app.GuiApp` (no Zenoh), and
:class:`human_bridge.gui.view.GuiView` draws it. Process level: the real ``khgrl human gui`` process fails loudly
without a display, writes offline screenshots, and runs its window (``SDL_VIDEODRIVER=dummy``) against a router
until stopped. Integration: a GUI in this process, connected to a real router + learner + actor, receives the
actor's frames; synthetic mouse events (``pygame.event.post``) produce real correction messages on the wire, and
the actor stores intervened transitions (episodes.csv, corrections.csv, the learner's checkpoint).
"""

from __future__ import annotations

import csv
import os
import subprocess
import time
from pathlib import Path

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402

from common.messages import ActorInfo, LearnerInfo  # noqa: E402
from common.protocol import Correction, Frame, RejectCounter, Scale, Status, decode, encode  # noqa: E402
from helpers import REPO, ProcGroup, python_main, read_json, unique_run, wait_for  # noqa: E402
from human_bridge.gui.app import GuiApp  # noqa: E402
from human_bridge.gui.view import GuiView  # noqa: E402


def _frame(actor="a0", episode=1, t=5, scenario="low_cov", intervening=False, scale=(15.0, 15.0), **kw) -> Frame:
    """A frame as it comes off the wire (encoded and decoded)."""
    f = Frame(actor=actor, episode=episode, t=t, phase=t / 399, robot=np.array([0.1, 0.5]),
              desired=np.array([0.1, 0.5]), mean=np.array([0.1, 0.5]), scale=np.array(scale),
              intervening=intervening, scenario=scenario, ret=-1.5, **kw)
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
    from common.render import SceneRenderer
    from common.scenarios import get_scenario

    sink = Sink()
    app = GuiApp(sink.send, sink.control, size=600)
    view = GuiView(app)
    app.offer(_frame(t=5))
    assert app.current == "a0" and app.actors["a0"].frame.t == 5
    view.draw(display)
    ref = SceneRenderer(get_scenario("low_cov"), None, None, size=600)
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(300, 150), button=1))
    assert app.dragging
    a, p, ep, t = sink.sent[-1]
    assert (a, ep, t) == ("a0", 1, 5)
    np.testing.assert_allclose(p, ref.pixel_to_world(np.array([300, 150])))
    _post_and_handle(app, _ev(pygame.MOUSEMOTION, pos=(320, 100), rel=(20, -50), buttons=(1, 0, 0)))
    n = len(sink.sent)
    app.offer(_frame(t=6))
    app.offer(_frame(t=7))
    assert len(sink.sent) == n + 2  # one active correction per frame while held
    np.testing.assert_allclose(sink.sent[-1][1], ref.pixel_to_world(np.array([320, 100])))
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
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(300, 650), button=1))  # the strip is not the scene
    assert not app.dragging and len(sink.sent) == n


def test_a_live_hold_ends_with_its_episode():
    sink = Sink()
    app = GuiApp(sink.send, sink.control)
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
    app = GuiApp(Sink().send)
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
    app = GuiApp(sink.send, sink.control)
    view = GuiView(app)
    app.offer(_frame("a0"))
    app.offer(_frame("a1", scenario="high_cov"))
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
    view.draw(display)  # the other actor's scenario
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(200, 200), button=1))
    assert sink.sent[-1][0] == "a1" and sink.sent[-1][1] is not None
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_q, mod=0, unicode="q"))
    assert app.quit and not app.dragging and sink.sent[-1] == ("a1", None, 1, 5)
    app2 = GuiApp(sink.send, sink.control)
    _post_and_handle(app2, _ev(pygame.KEYDOWN, key=pygame.K_ESCAPE, mod=0, unicode="\x1b"))
    assert app2.quit


def test_scale_table_drives_curve_and_band_and_bad_input_is_rejected(display):
    from common.env import build_world
    from human_bridge.client import read

    app = GuiApp(Sink().send)
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
    # what the wire brings in is decoded by the client (human_bridge.client.read) into typed messages
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
    from common.config import RunConfig, write_run_config
    from human_bridge.main import _resolve, build_parser

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
    p = subprocess.run(python_main("human_bridge.main") + ["gui", "--run", "r", "--connect", "tcp/127.0.0.1:1"],
                       cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)
    assert p.returncode == 3, p.stdout + p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "no display" in lines[0] and "DISPLAY" in lines[0], p.stderr
    # an explicit driver that cannot open a window: SDL's reason, same exit code
    p = subprocess.run(python_main("human_bridge.main") + ["gui", "--run", "r", "--connect", "tcp/127.0.0.1:1"],
                       cwd=REPO, env=_env(SDL_VIDEODRIVER="x11"), capture_output=True, text=True, timeout=60)
    assert p.returncode == 3 and "SDL could not open a window" in p.stderr, p.stdout + p.stderr


def test_screenshot_offline_writes_png(tmp_path):
    out = tmp_path / "gui.png"
    p = subprocess.run(python_main("human_bridge.main") + ["gui", "--screenshot", str(out), "--offline",
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
    from common.protocol import Keys
    from common.transport import Inbox, open_client

    run = unique_run("guiw")
    assert os.environ["SDL_VIDEODRIVER"] == "dummy"  # (set at the top of this module; the children inherit it)
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        gui = g.start("gui", python_main("human_bridge.main") + ["gui", "--run", run, "--connect", ep, "--fps", "20"])
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
    from common.process import StopFlag
    from common.protocol import Keys
    from common.transport import open_client
    from human_bridge.client import HumanClient
    from human_bridge.gui.main import GUI_KINDS, GuiSession

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
            app = net.app(actor="a0", run=run)
            view = GuiView(app)
            r = view.renderer("low_cov")  # the world is built before the actor's (short) episodes run
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
                mean = np.asarray(app.actors["a0"].frame.mean)
                px = r.world_to_pixel(mean + np.array([0.0, 0.05]))
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
    np.testing.assert_allclose(active[0].p_h, r.pixel_to_world(np.asarray(px, dtype=np.float64)))
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
    from learner.checkpoint import load_checkpoint_arrays

    arrays = load_checkpoint_arrays(run_dir / "learner" / "checkpoint")
    filled = arrays["provenance_actor"] >= 0
    assert int(filled.sum()) == sum(int(r["steps"]) for r in rows)
    assert int(arrays["intervened"][filled].sum()) == iv_steps
