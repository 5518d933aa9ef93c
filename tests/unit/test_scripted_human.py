"""The scripted human (human_bridge/scripted.py) and its single-process wrapper."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from khgrl.common.tasks.passage.env import PassageEnv
from khgrl.common.tasks.passage.scenarios import SCENARIOS, get_scenario
from khgrl.human_bridge.scripted import PAPER_EPISODES, HumanCorrectionWrapper, ScriptedHuman, ScriptedHumanConfig

from helpers import RecordingPublisher


# ------------------------------------------------------------------------------------ the human alone
@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_corrections_only_in_episodes_and_window(name):
    sc = get_scenario(name)
    h = ScriptedHuman(name, ScriptedHumanConfig(episodes=(2, 5)))
    lo, hi = sc.human_window
    assert h.guide.window == sc.human_window
    xs = np.linspace(0.0, 1.0, 201)
    for ep in range(1, 8):
        for x in xs:
            p = h.correction(ep, np.array([x, 0.123]))
            if ep in (2, 5) and lo <= x <= hi:
                assert p is not None
                assert p.shape == (2,)
                assert p[0] == x  # at the point the mean has reached in x
                assert p[1] == pytest.approx(h.path_y(x))  # on the safe path, whatever the mean's y
            else:
                assert p is None
    assert h.active_in(2) and not h.active_in(3)


def test_window_endpoints_inclusive_and_custom_window():
    h = ScriptedHuman("high_cov", ScriptedHumanConfig(episodes=(1,), window=(0.3, 0.4)))
    assert h.correction(1, np.array([0.3, 0.5])) is not None
    assert h.correction(1, np.array([0.4, 0.5])) is not None
    assert h.correction(1, np.array([0.29, 0.5])) is None
    assert h.correction(1, np.array([0.41, 0.5])) is None


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_path_through_waypoints_and_gaps(name):
    sc = get_scenario(name)
    h = ScriptedHuman(name)
    for x, y in sc.human_waypoints:
        assert h.path_y(x) == pytest.approx(y)
    for wall in sc.walls:
        assert wall.gap_lo < h.path_y(wall.x) < wall.gap_hi
    # piecewise linear between waypoints
    (x0, y0), (x1, y1) = sc.human_waypoints[1:3]
    assert h.path_y(0.5 * (x0 + x1)) == pytest.approx(0.5 * (y0 + y1))


def test_default_episodes_are_the_papers():
    assert ScriptedHumanConfig().episodes == PAPER_EPISODES == (4, 5, 10, 19, 20, 28, 29)


def test_noise_is_seeded():
    def stream(seed, noise=0.01):
        h = ScriptedHuman("high_cov", ScriptedHumanConfig(episodes=(1,), noise=noise, seed=seed))
        return np.array([h.correction(1, np.array([x, 0.5])) for x in np.linspace(0.25, 0.75, 50)])

    a, b, c = stream(0), stream(0), stream(1)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    clean = stream(0, noise=0.0)
    dev = a - clean
    assert 0.002 < dev.std() < 0.03  # noise of about the configured std
    h = ScriptedHuman("high_cov", ScriptedHumanConfig(episodes=(1,)))
    np.testing.assert_array_equal(clean[:, 1], [h.path_y(x) for x in clean[:, 0]])


def test_bad_scenarios():
    sc = get_scenario("high_cov")
    with pytest.raises(ValueError):
        ScriptedHuman(dataclasses.replace(sc, human_waypoints=()))
    with pytest.raises(ValueError):
        ScriptedHuman(dataclasses.replace(sc, human_waypoints=((0.5, 0.5), (0.4, 0.5))))
    with pytest.raises(ValueError):
        ScriptedHuman("nope")


# ------------------------------------------------------------------------------------ through the wrapper
class Recorder:
    def __init__(self) -> None:
        self.calls: list[tuple[int, list[dict]]] = []
        self.wrapper: HumanCorrectionWrapper | None = None

    def __call__(self, segment):
        self.calls.append((self.wrapper.episode, list(segment)))


@pytest.fixture(scope="module")
def run():
    """Three low_cov episodes with zero policy actions, the scripted human in episode 2 only."""
    env = PassageEnv("low_cov")
    human = ScriptedHuman("low_cov", ScriptedHumanConfig(episodes=(2,)))
    rec = Recorder()
    wrapper = HumanCorrectionWrapper(env, human, on_release=rec)
    rec.wrapper = wrapper
    episodes = []
    for _ in range(3):
        wrapper.reset(seed=0)
        steps = []
        done = False
        while not done:
            t = env.t
            policy = np.array([0.0, 0.0], dtype=np.float32)
            _, r, te, tr, info = wrapper.step(policy)
            steps.append(dict(t=t, info=info, mean=env.mapping.mean(t).copy()))
            done = te or tr
        episodes.append(dict(number=wrapper.episode, steps=steps, end=(te, tr)))
    return env, human, rec, episodes


def test_wrapper_counts_episodes_from_one(run):
    _, _, _, episodes = run
    assert [e["number"] for e in episodes] == [1, 2, 3]


def test_no_intervention_outside_configured_episodes(run):
    _, _, _, episodes = run
    for e in (episodes[0], episodes[2]):
        for s in e["steps"]:
            info = s["info"]
            assert not info["intervened"]
            np.testing.assert_array_equal(info["action"], [0.0, 0.0])


def test_intervened_exactly_in_window_with_expected_actions(run):
    env, human, _, episodes = run
    lo, hi = human.guide.window
    model = env.world.model
    n_iv = 0
    for s in episodes[1]["steps"]:
        info, mean, t = s["info"], s["mean"], s["t"]
        in_window = lo <= mean[0] <= hi
        assert info["intervened"] == in_window, (t, mean)
        if not in_window:
            np.testing.assert_array_equal(info["action"], [0.0, 0.0])
            continue
        n_iv += 1
        p_h = np.array([mean[0], human.path_y(mean[0])])
        np.testing.assert_array_equal(info["desired"], p_h)
        L = np.asarray(info["scale"])
        xi = np.linalg.solve(np.asarray(model.grid_projector)[t], p_h - mean)
        np.testing.assert_allclose(info["xi_h"], xi, rtol=1e-9)
        np.testing.assert_allclose(info["action"], np.clip(xi / L, -1, 1).astype(np.float32), rtol=1e-6)
    assert n_iv > 0


def test_on_release_gets_the_segment(run):
    _, _, rec, episodes = run
    assert len(rec.calls) == 1
    episode, segment = rec.calls[0]
    assert episode == 2
    iv = [s for s in episodes[1]["steps"] if s["info"]["intervened"]]
    assert len(segment) == len(iv)
    for d, s in zip(segment, iv):
        assert set(d) >= {"xi_h", "phase", "position"}
        np.testing.assert_array_equal(d["xi_h"], s["info"]["xi_h"])
        assert d["phase"] == s["info"]["phase"]
        np.testing.assert_array_equal(d["position"], s["info"]["desired"])
    # one contiguous segment in phase order
    phases = [d["phase"] for d in segment]
    assert phases == sorted(phases)


def test_episode_outcomes(run):
    """low_cov with zero actions: blocked at the second wall without the human; with it, through both gaps."""
    _, _, _, episodes = run
    for e in (episodes[0], episodes[2]):
        assert e["end"] == (True, False) and e["steps"][-1]["info"]["failure"]
    assert episodes[1]["end"][0] and episodes[1]["steps"][-1]["info"]["success"]


def test_wrapper_flushes_on_reset_and_releases_at_end():
    env = PassageEnv("high_cov")
    calls = []
    w = HumanCorrectionWrapper(
        env, ScriptedHuman("high_cov", ScriptedHumanConfig(episodes=(1,), window=(0.0, 1.0))), on_release=calls.append
    )
    w.reset(seed=0)
    for _ in range(5):
        w.step(np.zeros(2))
    assert env.intervening and calls == []
    w.reset(seed=0)  # a reset mid-intervention ends the segment
    assert len(calls) == 1 and len(calls[0]) == 5
    assert not env.intervening and w.episode == 2
    # episode 2 is not a human episode
    _, _, _, _, info = w.step(np.zeros(2))
    assert not info["intervened"]


def test_wrapper_without_callback():
    env = PassageEnv("high_cov")
    w = HumanCorrectionWrapper(env, ScriptedHuman("high_cov", ScriptedHumanConfig(episodes=(1,), window=(0.0, 1.0))))
    w.reset(seed=0)
    _, _, _, _, info = w.step(np.zeros(2))
    assert info["intervened"]
    w.reset(seed=0)


# ------------------------------------------------------------------------------------ the scripted client's answers
def _frames(name: str, episode: int, steps: int):
    from khgrl.common.wire.protocol import Frame

    env = PassageEnv(name)
    m = env.mapping
    for t in range(steps):
        yield Frame(actor="a0", episode=episode, t=t, phase=t / (env.horizon - 1), robot=m.mean(t), desired=m.mean(t),
                    mean=m.mean(t), scale=np.array([15.0, 15.0]), intervening=False, task=name,
                    next_mean=m.mean(t + 1), last=True if t == steps - 1 else None)


def test_scripted_answers_are_step_addressed_and_announce_the_next_help_episode():
    from khgrl.human_bridge.scripted import ScriptedAnswers

    name = "low_cov"
    human = ScriptedHuman(name, ScriptedHumanConfig(episodes=(2,)))
    stream = RecordingPublisher()
    answers = ScriptedAnswers(human, stream)
    env = PassageEnv(name)
    for f in _frames(name, 1, 50):  # the episode before the help episode: only the announcement
        answers.frame(f)
    assert len(stream.sent) == 1
    actor, p0, ep, t, step = stream.sent[0]
    assert (actor, ep, t, step) == ("a0", 2, 0, 0)  # lock-step for episode 2 announced with its step 0's word
    want0 = human.correction(2, env.mapping.mean(0))
    assert (p0 is None) == (want0 is None) and (p0 is None or np.array_equal(p0, want0))
    stream.sent.clear()
    for f in _frames(name, 2, env.horizon - 1):
        answers.frame(f)
    assert [s[4] for s in stream.sent] == list(range(1, env.horizon))  # every frame: a word for step t + 1
    for _, p_h, ep, t, step in stream.sent:
        want = human.correction(2, env.mapping.mean(step))
        assert ep == 2 and step == t + 1
        assert (p_h is None) == (want is None) and (p_h is None or np.array_equal(p_h, want))
    assert any(s[1] is not None for s in stream.sent)
    stream.sent.clear()
    for f in _frames(name, 3, 5):  # after the help episode: a hold left over is released once, then silence
        answers.frame(f)
    assert all(s[1] is None for s in stream.sent) and len(stream.sent) <= 1
