"""``khgrl human gui``: the pygame human-input client.

Unit level: synthetic frames and synthetic pygame events drive :class:`human_bridge.gui.GuiApp` (no Zenoh).
Integration: a GUI instance in this process, connected to a real router + learner + actor, receives the actor's
frames; synthetic mouse events (``pygame.event.post``) produce real correction messages on the wire, and the actor
stores intervened transitions (episodes.csv, corrections.csv, the learner's checkpoint). Headless
(``SDL_VIDEODRIVER=dummy``).
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402

from common.protocol import decode, encode  # noqa: E402
from helpers import REPO, ProcGroup, read_json, unique_run, wait_for  # noqa: E402


def _frame(actor="a0", episode=1, t=5, scenario="low_cov", intervening=False, scale=(15.0, 15.0), **kw) -> bytes:
    fields = dict(actor=actor, episode=episode, t=t, phase=t / 399, robot=[0.1, 0.5], desired=[0.1, 0.5],
                  mean=[0.1, 0.5], scale=list(scale), intervening=intervening, scenario=scenario, ret=-1.5)
    fields.update(kw)
    return encode("frame", actor, t, **fields)


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


# ------------------------------------------------------------------------------------------ unit level
def test_drag_sends_pointer_position_each_frame_and_release(display):
    from common.render import SceneRenderer
    from common.scenarios import get_scenario
    from human_bridge.gui import GuiApp

    sink = Sink()
    app = GuiApp(sink.send, sink.control, size=600)
    app.offer("frame", "k/a0", _frame(t=5))
    assert app.current == "a0" and app.actors["a0"].frame["t"] == 5
    app.draw(display)  # builds the world / renderer for the frame's scenario
    ref = SceneRenderer(get_scenario("low_cov"), None, None, size=600)
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(300, 150), button=1))
    assert app.dragging
    a, p, ep, t = sink.sent[-1]
    assert (a, ep, t) == ("a0", 1, 5)
    np.testing.assert_allclose(p, ref.pixel_to_world(np.array([300, 150])))
    _post_and_handle(app, _ev(pygame.MOUSEMOTION, pos=(320, 100), rel=(20, -50), buttons=(1, 0, 0)))
    n = len(sink.sent)
    app.offer("frame", "k/a0", _frame(t=6))
    app.offer("frame", "k/a0", _frame(t=7))
    assert len(sink.sent) == n + 2  # one active correction per frame while held
    np.testing.assert_allclose(sink.sent[-1][1], ref.pixel_to_world(np.array([320, 100])))
    assert sink.sent[-1][2:] == (1, 7)
    # keepalive while no frame arrives
    app.last_send -= 1.0
    app.keepalive()
    assert len(sink.sent) == n + 3 and sink.sent[-1][1] is not None
    app.draw(display)  # the drag is drawn (correction cross, HUMAN badge)
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONUP, pos=(320, 100), button=1))
    assert not app.dragging and sink.sent[-1][1] is None
    n = len(sink.sent)
    app.offer("frame", "k/a0", _frame(t=8))
    app.keepalive()
    assert len(sink.sent) == n  # released: nothing more
    # a press on the strip below the scene is not a drag
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(300, 650), button=1))
    assert not app.dragging and len(sink.sent) == n


def test_keys_pause_overlays_tab_quit(display):
    from human_bridge.gui import GuiApp

    sink = Sink()
    app = GuiApp(sink.send, sink.control)
    app.offer("frame", "k/a0", _frame("a0"))
    app.offer("frame", "k/a1", _frame("a1", scenario="high_cov"))
    assert app.current == "a0"
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_SPACE, mod=0, unicode=" "))
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_SPACE, mod=0, unicode=" "))
    assert sink.controls == ["pause", "resume"]
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_o, mod=0, unicode="o"))
    assert app.overlays is False
    app.draw(display)
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(200, 200), button=1))
    assert app.dragging and sink.sent[-1][0] == "a0"
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_TAB, mod=0, unicode="\t"))
    assert app.current == "a1" and not app.dragging
    assert sink.sent[-1][0] == "a0" and sink.sent[-1][1] is None  # released a0 before switching
    app.draw(display)  # the other actor's scenario
    _post_and_handle(app, _ev(pygame.MOUSEBUTTONDOWN, pos=(200, 200), button=1))
    assert sink.sent[-1][0] == "a1" and sink.sent[-1][1] is not None
    _post_and_handle(app, _ev(pygame.KEYDOWN, key=pygame.K_q, mod=0, unicode="q"))
    assert app.quit and not app.dragging and sink.sent[-1] == ("a1", None, 1, 5)
    app2 = GuiApp(sink.send, sink.control)
    _post_and_handle(app2, _ev(pygame.KEYDOWN, key=pygame.K_ESCAPE, mod=0, unicode="\x1b"))
    assert app2.quit


def test_scale_table_drives_curve_and_band_and_bad_input_is_rejected(display):
    from common.env import build_world
    from human_bridge.gui import GuiApp

    app = GuiApp(Sink().send)
    app.offer("frame", "k/a0", _frame(scale=(15.0, 15.0)))
    v = app.actors["a0"]
    phases, L = app.scale_curve(v)
    assert np.all(L == 15.0)  # flat at the frame's scale without a scale message
    w = build_world("low_cov")
    n = w.model.n_points
    table = np.c_[np.linspace(5, 30, n), np.full(n, 15.0)]
    app.offer("scale", "k/a0", encode("scale", "a0", 0, actor="a0", model={"default": [15.0, 15.0]}, table=table))
    phases, L = app.scale_curve(v)
    np.testing.assert_allclose(L, table)
    band = app.band(v)
    half = np.einsum("nij,nj->ni", np.abs(w.model.grid_projector), table)
    np.testing.assert_allclose(band[:, 1] - band[:, 0], 2 * half)
    app.draw(display)
    app.offer("frame", "k/a0", b"\xc1garbage")
    app.offer("frame", "k/a0", _frame(ret=float("nan")))
    app.offer("scale", "k/a0", encode("scale", "a0", 1, actor="a0", model={}, table=-table))
    assert app.rejects.by_kind() == {"frame": 2, "scale": 1}
    np.testing.assert_allclose(app.scale_curve(v)[1], table)


def test_screenshot_offline_writes_png(tmp_path):
    out = tmp_path / "gui.png"
    env = dict(os.environ, SDL_VIDEODRIVER="dummy", PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, "-m", "deploy.cli", "human", "gui", "--screenshot", str(out), "--offline",
                        "--scenario", "low_cov", "--size", "400"], cwd=REPO, env=env, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    img = pygame.image.load(str(out))
    assert img.get_size() == (400, 400 + 80 + 90)


def test_launcher_accepts_human_gui():
    from deploy.launcher import build_parser

    assert build_parser().parse_args(["--human", "gui"]).human == "gui"
    from human_bridge.service import build_parser as human_parser

    a = human_parser().parse_args(["gui", "--run", "r", "--connect", "tcp/127.0.0.1:1", "--scenario", "low_cov",
                                   "--actor", "*", "--seed", "0", "--episodes", "2"])
    assert a.client == "gui" and a.actor == "*"


# ---------------------------------------------------------------------------------- real router + actor
@pytest.mark.integration
@pytest.mark.timeout(240)
def test_gui_mouse_drag_over_real_actor_produces_intervened_transitions(tmp_path, display):
    import zenoh

    from common.protocol import Keys
    from common.session import StopFlag, open_client
    from human_bridge.gui import GuiApp, GuiSession

    run = unique_run("gui")
    run_dir = tmp_path / "run"
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "100000", run_dir=run_dir)
        actor = g.actor(run, ep, "--scenario", "low_cov", "--method", "khgrl", "--episodes", "2", "--rate", "50",
                        "--learning-starts", "16", "--max-lead", "100000", run_dir=run_dir)
        keys = Keys(run)
        wire: list[dict] = []
        statuses: dict = {}
        with open_client(ep) as session:
            net = GuiSession(session, keys, "gui", "a0", StopFlag())
            spy = session.declare_subscriber(keys.correction("*"), lambda s: wire.append(
                decode("correction", s.payload.to_bytes())))
            st = session.declare_subscriber(keys.status("actor", "a0"), lambda s: statuses.update(
                decode("status", s.payload.to_bytes())["info"]))
            app = GuiApp(net.send, net.control, actor="a0", client="gui", run=run)

            def tick(*events):
                net.pump(app)
                _post_and_handle(app, *events)
                app.keepalive()
                app.draw(display)
                pygame.display.flip()

            def at(t_min):
                def ok():
                    tick()
                    v = app.actors.get("a0")
                    return v is not None and v.frame is not None and v.frame["episode"] == 1 and v.frame["t"] >= t_min
                return ok

            try:
                wait_for(at(30), 120, "frames of episode 1 from the actor", procs=[actor, learner])
                mean = np.asarray(app.actors["a0"].frame["mean"])
                r = app.renderer("low_cov")
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
                # pause / resume the actor with the space bar
                tick(_ev(pygame.KEYDOWN, key=pygame.K_SPACE, mod=0, unicode=" "))

                def paused():
                    tick()
                    return statuses.get("paused") is True
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
                net.close(app)
        assert actor.wait(120) == 0, actor.tail()
        learner.stop(30)  # the checkpoint the actor asked for at its flush is on disk

    # real corrections were on the wire: active ones with the pointer's P_h, then one release
    mine = [m for m in wire if m["client"] == "gui"]
    active = [m for m in mine if m["active"]]
    assert len(active) >= 10, len(active)
    assert mine[-1]["active"] is False
    assert all(m["actor"] == "a0" for m in mine)
    drag_eps = {m["episode"] for m in mine}  # a drag may run over the end of a (short, random-policy) episode
    np.testing.assert_allclose(active[0]["p_h"], r.pixel_to_world(np.asarray(px, dtype=np.float64)))
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
    from learner.service import load_checkpoint_arrays

    ck = run_dir / "learner" / "checkpoint"
    state, arrays = read_json(ck / "state.json"), load_checkpoint_arrays(ck)
    n = state["replay"]["size"] if state["replay"]["full"] else state["replay"]["pos"]
    assert n == sum(int(r["steps"]) for r in rows)
    assert int(arrays["intervened"][:n].sum()) == iv_steps
