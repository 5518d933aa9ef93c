"""A real actor of a task whose scene changes every episode (deploy/examples/reach_task.py) sends each episode's
adapted KMP on the episode's first frame, and a GUI fed from the wire draws that episode's mean, band and via-point
(issue 22, point 1). Forged scene fields on the same key are refused and counted. One run (router, learner, actor;
3 episodes of 40 steps) serves every assertion."""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"

import msgpack  # noqa: E402
import numpy as np  # noqa: E402
import pygame  # noqa: E402
import pytest  # noqa: E402
from khgrl.common.tasks.api import load_task  # noqa: E402
from khgrl.common.tasks.kgrl_env import KGRLEnv  # noqa: E402
from khgrl.common.wire.checks import pack_array  # noqa: E402
from khgrl.common.wire.protocol import Frame, Keys, encode  # noqa: E402
from khgrl.human_bridge.gui.app import GuiApp  # noqa: E402
from khgrl.human_bridge.gui.view import GuiView  # noqa: E402

from helpers import ProcGroup, unique_run, wait_for  # noqa: E402

SPEC = "khgrl.deploy.examples.reach_task:make_task"
SEED = 5
EPISODES = 3


def _forged(keys: Keys, session, f: Frame) -> None:
    """Publish on the actor's frame key: ``f`` at t = 3 with its scene (refused on decoding), and ``f`` with a
    scene one grid point short (decodes; the GUI refuses it against the task's N)."""
    m = msgpack.unpackb(encode(f, "a0", 900), raw=False)
    session.put(keys.frame("a0"), msgpack.packb({**m, "t": 3}, use_bin_type=True))
    short = {**m, "episode": 99, "scene_mean": pack_array(f.scene_mean[:-1]),
             "scene_projector": pack_array(f.scene_projector[:-1])}
    session.put(keys.frame("a0"), msgpack.packb(short, use_bin_type=True))


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_actor_sends_each_episodes_scene_and_the_gui_draws_it(tmp_path):
    from khgrl.common.delivery.transport import open_client
    from khgrl.common.process import StopFlag
    from khgrl.common.tasks.render_parts import COLORS
    from khgrl.human_bridge.client import HumanClient

    local = KGRLEnv(load_task(SPEC), seed=SEED)
    task = local.descriptor(SPEC)
    run, run_dir = unique_run("scn"), tmp_path / "run"
    keys = Keys(run)
    frames: list[Frame] = []
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        learner = g.learner(run, ep, "--learning-starts", "100000", run_dir=run_dir)
        with open_client(ep) as session:
            link = HumanClient(session, keys, "viewer", StopFlag(), "a0", ("frame",))
            actor = g.actor(run, ep, "--task", SPEC, "--seed", str(SEED), "--episodes", str(EPISODES),
                            "--learning-starts", "16", "--max-lead", "100000", run_dir=run_dir)

            def drain(until):
                while (got := link.next(0.05)) is not None:
                    frames.append(got[1])
                return until()

            try:
                wait_for(lambda: drain(lambda: any(f.last and f.episode == EPISODES for f in frames)), 180,
                         "the actor's last frame", procs=[actor, learner])
                _forged(keys, session, next(f for f in frames if f.has_scene))
                wait_for(lambda: drain(lambda: link.rejects.total >= 1 and frames[-1].episode == 99), 30,
                         "the forged frames")
            finally:
                link.close()
        assert actor.wait(120) == 0, actor.tail()
        learner.stop(30)

    forged = frames.pop()
    assert forged.episode == 99 and link.rejects.by_kind() == {"frame": 1}  # the t = 3 one, refused on decoding
    assert all(f.task == "reach" for f in frames) and len(frames) == EPISODES * local.horizon
    scenes = {f.episode: f for f in frames if f.has_scene}
    assert sorted(scenes) == list(range(1, EPISODES + 1)) and all(f.t == 0 for f in scenes.values())
    ends = []
    for e, f in scenes.items():  # what the actor sent is the episode's adapted KMP (seeded: reproduced here)
        local.reset_episode(e)
        np.testing.assert_allclose(f.scene_mean, local.mapping.model.grid_mean, atol=1e-9)
        np.testing.assert_allclose(f.scene_projector, local.mapping.model.grid_projector, atol=1e-9)
        np.testing.assert_allclose(f.scene_via, [[step / (local.horizon - 1), *pos] for step, pos in local.via_points])
        for step, pos in local.via_points:
            assert np.linalg.norm(f.scene_mean[step] - pos) < 1e-3  # the adapted mean passes through the via-points
        per_step = [g.mean for g in frames if g.episode == e]
        np.testing.assert_allclose(per_step, f.scene_mean)  # every frame's mean is the episode's adapted one
        ends.append(f.scene_mean[-1])
    assert min(np.linalg.norm(a - b) for i, a in enumerate(ends) for b in ends[i + 1:]) > 1e-3  # scenes differ

    # a GUI fed these frames: each episode's own mean and via-point; one that joins mid-episode 1: the demos' first
    pygame.font.init()
    for joined in (0, 5):
        app = GuiApp(lambda *a: None, task=task, size=400)
        view, surf = GuiView(app), pygame.Surface((app.width, app.height))
        for f in frames[joined:]:
            app.offer(f)
            v = app.actors["a0"]
            want = scenes[f.episode].scene_mean if (f.episode > 1 or not joined) else None
            got = view.frame_state(v).mean
            assert (got is None) == (want is None) and (want is None or np.array_equal(got, want))
            if f.t in (0, local.horizon - 1):
                view.draw(surf)
                img = pygame.surfarray.array3d(surf).swapaxes(0, 1)
                x, y = (int(round(c)) for c in app.layout.to_pixel(0, scenes[f.episode].scene_via[0, 1:]))
                patch = img[y - 3:y + 4, x - 3:x + 4].astype(int)
                drawn = bool(np.any(np.all(np.abs(patch - COLORS["via"]) <= 40, axis=-1)))
                assert drawn == (want is not None), (joined, f.episode, f.t)
        app.offer(forged)
        assert app.rejects.by_kind() == {"frame": 1} and app.actors["a0"].frame.episode == EPISODES  # another grid
