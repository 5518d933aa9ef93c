"""Frames, the GUI and rendered frames show each episode's adapted KMP (issue 22, point 1): the ``frame`` message's
``scene_*`` fields (sent on the first frame of an episode of a varying-scene task), the GUI's per-actor episode scene,
the renderer's per-episode mean and via-points, and the scripted client's per-episode means."""

from __future__ import annotations

import logging
import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import msgpack  # noqa: E402
import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from khgrl.actor.telemetry import frame as actor_frame  # noqa: E402
from khgrl.common.tasks import scene_frame  # noqa: E402
from khgrl.common.tasks.api import load_task  # noqa: E402
from khgrl.common.tasks.kgrl_env import KGRLEnv  # noqa: E402
from khgrl.common.tasks.passage.env import PassageEnv  # noqa: E402
from khgrl.common.tasks.render import TaskFrame, TaskRenderer, frame_from_env  # noqa: E402
from khgrl.common.tasks.scene import MAX_VIA_POINTS  # noqa: E402
from khgrl.common.wire.checks import pack_array  # noqa: E402
from khgrl.common.wire.messages import MAX_FRAME_VIA  # noqa: E402
from khgrl.common.wire.protocol import Dims, Frame, ProtocolError, decode, encode  # noqa: E402
from khgrl.human_bridge.gui.app import GuiApp  # noqa: E402
from khgrl.human_bridge.gui.main import synthetic_frames  # noqa: E402
from khgrl.human_bridge.gui.view import GuiView  # noqa: E402
from khgrl.human_bridge.scripted import ScriptedAnswers, ScriptedHuman, ScriptedHumanConfig  # noqa: E402

from helpers import RecordingPublisher  # noqa: E402

REACH = "khgrl.deploy.examples.reach_task:make_task"
SCENE_KEYS = {"scene_mean", "scene_projector", "scene_via"}


@pytest.fixture(scope="module")
def reach() -> KGRLEnv:
    return KGRLEnv(load_task(REACH), seed=0)


def _step_frames(env: KGRLEnv, episode: int, steps: int) -> list[Frame]:
    """The actor's frames (actor/telemetry.py ``frame``) of ``steps`` zero-action steps of ``episode``."""
    env.reset_episode(episode)
    out, ret = [], 0.0
    for _ in range(steps):
        _, r, term, trunc, info = env.step(np.zeros(env.action_space.shape, np.float32))
        ret += float(r)
        out.append(actor_frame(env, "a0", episode, info, int(info["t"]), False, ret, bool(term or trunc)))
    return out


def _wire(f: Frame) -> dict:
    return msgpack.unpackb(encode(f, "a0", 0), raw=False)


# ------------------------------------------------------------------------------------------------ the wire
def test_first_frame_of_an_adapted_episode_carries_its_scene(reach: KGRLEnv) -> None:
    frames = _step_frames(reach, 1, 3)
    model = reach.mapping.model
    f0 = decode(Frame, encode(frames[0], "a0", 0), Dims(out=2, horizon=reach.horizon))
    np.testing.assert_array_equal(f0.scene_mean, model.grid_mean)
    np.testing.assert_array_equal(f0.scene_projector, model.grid_projector)
    np.testing.assert_array_equal(f0.scene_via, [[step / (reach.horizon - 1), *pos] for step, pos in reach.via_points])
    assert not np.allclose(f0.scene_mean, reach.world.model.grid_mean)  # the adapted mean, not the demonstrations'
    assert not any(SCENE_KEYS & set(_wire(f)) for f in frames[1:])  # only the episode's first frame has them
    with pytest.raises(ProtocolError, match="scene_mean: expected shape"):
        decode(Frame, encode(frames[0], "a0", 0), Dims(out=2, horizon=reach.horizon + 1))  # the receiver's N


def test_fixed_scene_frames_have_no_scene_fields() -> None:
    env = PassageEnv("high_cov")
    env.reset()
    _, _, _, _, info = env.step(np.zeros(2, np.float32))
    f = actor_frame(env, "a0", 1, info, 0, False, 0.0, False)
    assert not f.has_scene and not SCENE_KEYS & set(_wire(f))
    # a varying scene that the actor does not adapt (--no-adapt): the descriptor's mean is the episode's, none sent
    plain = KGRLEnv(load_task(REACH), seed=0, adapt=False)
    assert not any(f.has_scene for f in _step_frames(plain, 1, 2))


def _scene_map(o: int = 2, n: int = 5, **over) -> dict:
    m = _wire(Frame(actor="a0", episode=1, t=0, phase=0.0, robot=np.zeros(o), desired=np.zeros(o), mean=np.zeros(o),
                    scale=np.ones(o), intervening=False, task="reach"))
    m.update(scene_mean=pack_array(np.zeros((n, o))), scene_projector=pack_array(np.zeros((n, o, o))),
             scene_via=pack_array(np.array([[1.0] + [0.5] * o])))
    m.update(over)
    return {k: v for k, v in m.items() if v is not None}


@pytest.mark.parametrize("over, reason", [
    (dict(t=3), "only with an episode's first frame"),
    (dict(scene_mean=None), "scene_projector without scene_mean"),
    (dict(scene_projector=pack_array(np.zeros((4, 2, 2)))), "scene_projector: expected shape"),
    (dict(scene_mean=pack_array(np.zeros((5, 3)))), "scene_mean: expected shape"),
    (dict(scene_mean=pack_array(np.zeros((5, 2), np.float32))), "dtype"),
    (dict(scene_mean=pack_array(np.full((5, 2), np.nan))), "NaN or inf"),
    (dict(scene_mean=pack_array(np.zeros((1, 2))), scene_projector=None), "grid points outside"),
    (dict(scene_via=pack_array(np.array([[1.5, 0.0, 0.0]]))), "phase outside"),
    (dict(scene_via=pack_array(np.zeros((0, 3)))), "via-points outside"),
    (dict(scene_via=pack_array(np.zeros((MAX_FRAME_VIA + 1, 3)))), "via-points outside"),
    (dict(scene_via=pack_array(np.zeros((1, 2)))), "scene_via: expected shape"),
    (dict(scene_via={"dtype": "<f8", "shape": [1, 3], "data": b"\0" * 8}), "do not match"),
])
def test_bad_scene_fields_are_refused(over: dict, reason: str) -> None:
    payload = msgpack.packb(_scene_map(**over), use_bin_type=True)
    with pytest.raises(ProtocolError, match=reason):
        decode(Frame, payload)


def test_a_good_scene_map_decodes_and_limits_agree() -> None:
    f = decode(Frame, msgpack.packb(_scene_map(), use_bin_type=True), Dims(out=2, horizon=5))
    assert f.scene_mean.shape == (5, 2) and f.scene_projector.shape == (5, 2, 2) and f.scene_via.shape == (1, 3)
    assert MAX_FRAME_VIA == MAX_VIA_POINTS


class _Model:
    def __init__(self, n: int, o: int) -> None:
        rng = np.random.default_rng(n)
        self.grid_mean, self.grid_projector = rng.normal(size=(n, o)), rng.normal(size=(n, o, o))


class _Env:
    """What frame_scene reads of a KGRLEnv: varies, via_points, mapping.model."""

    varies = True

    def __init__(self, n: int, o: int) -> None:
        self.mapping = type("M", (), {"model": _Model(n, o)})()
        self.via_points = [(n - 1, np.full(o, 0.25))]


def _scene_frame(n: int, o: int) -> Frame:
    z = np.zeros(o)
    return Frame(actor="a0", episode=1, t=0, phase=0.0, robot=z, desired=z, mean=z, scale=z + 1, intervening=False,
                 task="t", next_mean=z, obs=np.zeros(256), **scene_frame.frame_scene(_Env(n, o), 0, Frame.MAX_BYTES))


def test_frame_size_n400_o3_fits_and_a_long_grid_degrades_with_one_log_line(caplog, monkeypatch) -> None:
    f = _scene_frame(400, 3)
    assert f.scene_projector is not None and len(encode(f, "a0", 2**40)) <= Frame.MAX_BYTES
    worst = _scene_frame(400, 3).replace(obs=np.full(256, 1e300), robot=np.full(3, 1e300))
    assert len(encode(worst, "a0", 2**40)) <= Frame.MAX_BYTES
    monkeypatch.setattr(scene_frame, "_warned", set())
    with caplog.at_level(logging.WARNING, logger="khgrl.actor"):
        big = [_scene_frame(2000, 3) for _ in range(3)]  # projector 144 kB: mean and via-points only
        huge = _scene_frame(100_000, 3)  # mean 2.4 MB: via-points only
    assert all(f.scene_mean is not None and f.scene_projector is None for f in big)
    assert huge.scene_mean is None and huge.scene_via is not None
    for f in (*big, huge):
        assert len(encode(f, "a0", 0)) <= Frame.MAX_BYTES
    assert [r.getMessage().split(" does not fit")[0] for r in caplog.records] == [
        "frames: the adapted projector (N = 2000, O = 3)", "frames: the adapted mean (N = 100000, O = 3)"]
    assert scene_frame.frame_scene(_Env(400, 3), 1, Frame.MAX_BYTES) == {}


# ------------------------------------------------------------------------------------------------ rendering
def _near(img: np.ndarray, xy, rgb, r: int = 3) -> bool:
    """Whether a pixel within ``r`` of ``xy`` has colour ``rgb`` (+- 40 per channel)."""
    x, y = (int(round(c)) for c in xy)
    patch = img[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1].astype(int)
    return bool(np.any(np.all(np.abs(patch - np.array(rgb)) <= 40, axis=-1)))


def test_gif_frames_draw_each_episodes_adapted_mean(reach: KGRLEnv) -> None:
    from khgrl.common.tasks.render_parts import COLORS

    renderer = TaskRenderer(reach.descriptor())  # made once from the descriptor, as khgrl eval --gif does
    imgs, ends = [], []
    for e in (1, 2):
        reach.reset_episode(e)
        reach.step(np.zeros(2, np.float32))
        frame = frame_from_env(reach)
        np.testing.assert_array_equal(frame.mean, reach.mapping.model.grid_mean)
        imgs.append(renderer.render_rgb(frame, show_demos=False))
        ends.append(renderer.to_pixel(0, reach.mapping.model.grid_mean[-1]))
    assert np.linalg.norm(ends[0] - ends[1]) > 20  # two placements, far apart on the image
    for k in (0, 1):  # each image has the via marker / mean end at its own target, not at the other's
        assert _near(imgs[k], ends[k], COLORS["via"]) and not _near(imgs[1 - k], ends[k], COLORS["via"])
        assert not _near(imgs[k], ends[1 - k], COLORS["mean"], r=2)
    for k, e in enumerate((1, 2)):  # the red line runs along the adapted mean's last segment
        reach.reset_episode(e)
        a, b = (renderer.to_pixel(0, p) for p in reach.mapping.model.grid_mean[-2:])
        assert _near(imgs[k], 0.5 * (a + b), COLORS["mean"], r=1)
    # the descriptor's (demonstrations') mean ends at DEMO_TARGET; the adapted ones do not
    demo_end = renderer.to_pixel(0, reach.world.model.grid_mean[-1])
    assert np.linalg.norm(ends[0] - demo_end) > 20


def test_the_eval_gif_recorder_shows_each_scene(reach: KGRLEnv) -> None:
    """``khgrl eval --gif`` (deploy/tools/gif.py, unchanged) gets each episode's scene through frame_from_env."""
    from khgrl.common.tasks.render_parts import COLORS
    from khgrl.deploy.tools.gif import GifRecorder

    gif = GifRecorder(reach)
    ends = []
    for e in (1, 2):
        reach.reset_episode(e)
        reach.step(np.zeros(2, np.float32))
        gif(reach, False)
        ends.append(gif.renderer.to_pixel(0, reach.via_points[0][1]))
    for k in (0, 1):
        assert _near(gif.frames[k], ends[k], COLORS["via"]) and not _near(gif.frames[1 - k], ends[k], COLORS["via"])


def test_a_fixed_scene_renders_as_without_scene_fields() -> None:
    """frame_from_env of a fixed-scene task brings no scene: the image is the one the renderer drew before issue 22
    (checked against main's renderer by hand: identical arrays for passage high_cov / low_cov and own_task)."""
    env = PassageEnv("high_cov")
    env.reset()
    for _ in range(5):
        env.step(np.full(2, 0.3, np.float32))
    frame = frame_from_env(env)
    assert frame.mean is None and frame.via is None
    r = TaskRenderer(env.descriptor(), legend=True)
    old = TaskFrame(position=frame.position, desired=frame.desired, phase=frame.phase, t=frame.t, trail=frame.trail,
                    band=frame.band, text=frame.text)
    assert np.array_equal(r.render_rgb(frame), r.render_rgb(old))


# ------------------------------------------------------------------------------------------------ the GUI
def test_gui_draws_the_episodes_adapted_mean_and_falls_back_mid_episode(reach: KGRLEnv) -> None:
    from khgrl.common.tasks.render_parts import COLORS

    pygame.font.init()
    app = GuiApp(lambda *a: None, task=reach.descriptor(), size=400)
    view = GuiView(app)
    surf = pygame.Surface((app.width, app.height))
    ep1 = _step_frames(reach, 1, 3)
    adapted1 = reach.mapping.model
    for f in ep1:
        app.offer(decode(Frame, encode(f, "a0", 0)))
    v = app.actors["a0"]
    state = view.frame_state(v)
    np.testing.assert_array_equal(state.mean, adapted1.grid_mean)
    band = view.band(v)  # about the adapted mean, with the adapted projector
    half = np.einsum("nij,nj->ni", np.abs(adapted1.grid_projector), np.broadcast_to(v.frame.scale, (reach.horizon, 2)))
    np.testing.assert_allclose(band[:, 1], adapted1.grid_mean + half)
    view.draw(surf)
    img = pygame.surfarray.array3d(surf).swapaxes(0, 1)
    end1 = app.layout.to_pixel(0, adapted1.grid_mean[-1])
    assert _near(img, end1, COLORS["via"])  # the via-point's marker where the adapted mean ends
    # a GUI that sees episode 2 from its step 2 on (its first frame missed): the demonstrations' mean
    ep2 = _step_frames(reach, 2, 3)
    app.offer(decode(Frame, encode(ep2[2], "a0", 0)))
    assert v.scene is None and view.frame_state(v).mean is None
    np.testing.assert_allclose(view.band(v)[:, 1] - view.band(v)[:, 0],
                               2 * np.einsum("nij,nj->ni", np.abs(app.task.projector),
                                             np.broadcast_to(v.frame.scale, (reach.horizon, 2))))
    view.draw(surf)
    img2 = pygame.surfarray.array3d(surf).swapaxes(0, 1)
    assert not _near(img2, end1, COLORS["via"])
    # episode 3 from its first frame: its own scene
    ep3 = _step_frames(reach, 3, 1)
    app.offer(decode(Frame, encode(ep3[0], "a0", 0)))
    np.testing.assert_array_equal(view.frame_state(v).mean, reach.mapping.model.grid_mean)


def test_gui_refuses_a_scene_of_another_grid(reach: KGRLEnv) -> None:
    app = GuiApp(lambda *a: None, task=reach.descriptor(), size=400)
    f = _step_frames(reach, 1, 1)[0]
    bad = f.replace(scene_mean=f.scene_mean[:-1], scene_projector=f.scene_projector[:-1])
    app.offer(decode(Frame, encode(bad, "a0", 0)))
    assert "a0" not in app.actors and app.rejects.by_kind() == {"frame": 1}
    app.offer(decode(Frame, encode(f, "a0", 1)))
    assert app.actors["a0"].scene is not None


def test_offline_synthetic_frames_carry_the_scene(reach: KGRLEnv) -> None:
    frames = synthetic_frames(reach, steps=4, drag_from=99)
    assert frames[0].has_scene and not any(f.has_scene for f in frames[1:])
    np.testing.assert_array_equal(frames[0].scene_mean, reach.mapping.model.grid_mean)


# ------------------------------------------------------------------------------------------------ scripted client
def test_scripted_answers_use_the_current_episodes_mean() -> None:
    """The step-0 word announced for the next help episode comes from the latest episode's mean at step 0 (a
    varying scene's mean moves every episode), not from the first episode's."""
    human = ScriptedHuman(lambda mean: np.asarray(mean) + [0.0, 0.1], ScriptedHumanConfig(episodes=(3,)))
    stream = RecordingPublisher()
    answers = ScriptedAnswers(human, stream)

    def frames(ep: int, m0: np.ndarray):
        for t in range(3):
            m = m0 + 0.01 * t
            yield Frame(actor="a0", episode=ep, t=t, phase=t / 2, robot=m, desired=m, mean=m, scale=np.ones(2),
                        intervening=False, task="reach", next_mean=m + 0.01, last=True if t == 2 else None)

    for f in frames(1, np.array([0.1, 0.2])):
        answers.frame(f)
    assert stream.sent == []
    for f in frames(2, np.array([-0.4, 0.3])):
        answers.frame(f)
    (actor, p0, ep, t, step), = [s for s in stream.sent if s[4] == 0]  # (the rest: a release of that word)
    assert (actor, ep, step) == ("a0", 3, 0)
    np.testing.assert_allclose(p0, [-0.4, 0.4])
