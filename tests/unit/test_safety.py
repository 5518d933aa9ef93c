"""The rate limiter between P_t and the robot (common/tasks/safety.py) and its place in KGRLEnv."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.config.settings import resolve
from khgrl.common.tasks.api import load_task
from khgrl.common.tasks.delta import largest_step
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.common.tasks.safety import RateLimiter

LOW, HIGH = np.zeros(2), np.ones(2)


def _run(lim: RateLimiter, targets: np.ndarray) -> np.ndarray:
    return np.array([lim.limit(p)[0] for p in targets])


def test_no_step_and_no_change_of_step_above_the_limits_whatever_is_asked():
    rng = np.random.default_rng(0)
    lim = RateLimiter(0.02, 0.005, LOW - 1, HIGH + 1)
    lim.reset(np.full(2, 0.5))
    sent = _run(lim, rng.uniform(-1, 2, size=(500, 2)))  # far jumps every step
    steps = np.diff(np.vstack([[0.5, 0.5], sent]), axis=0)
    assert np.max(np.abs(steps)) <= 0.02 + 1e-12
    assert np.max(np.abs(np.diff(np.vstack([[0.0, 0.0], steps]), axis=0))) <= 0.005 + 1e-12


def test_the_workspace_edge_is_approached_within_the_limits_too():
    """Before: the box clipped a position after the acceleration limit, so a target beyond the edge stopped the robot
    there in one step (the change of step as large as the speed; seen at the passage world's edge, issue 33)."""
    rng = np.random.default_rng(1)
    lim = RateLimiter(0.02, 0.005, LOW, HIGH)
    lim.reset(np.full(2, 0.5))
    targets = np.repeat(rng.uniform(-1.0, 2.0, size=(60, 2)), 25, axis=0)  # mostly beyond an edge, held a while
    sent = _run(lim, targets)
    steps = np.diff(np.vstack([[0.5, 0.5], sent]), axis=0)
    assert np.any(sent == LOW) and np.any(sent == HIGH)  # it went to the edges
    assert np.all(sent >= LOW) and np.all(sent <= HIGH) and np.max(np.abs(steps)) <= 0.02 + 1e-12
    assert np.max(np.abs(np.diff(np.vstack([[0.0, 0.0], steps]), axis=0))) <= 0.005 + 1e-12


def test_a_far_target_is_reached_at_the_speed_limit_then_held_without_a_jump():
    lim = RateLimiter(0.02, 0.005, LOW, HIGH)
    lim.reset(np.zeros(2))
    sent = _run(lim, np.tile([[0.8, 0.1]], (200, 1)))
    assert np.allclose(sent[-1], [0.8, 0.1], atol=1e-9)  # it gets there
    assert np.max(np.abs(np.diff(sent[:, 0]))) == pytest.approx(0.02)  # at full speed on the way
    assert np.max(sent[:, 0]) <= 0.8 + 0.02  # braking: it passes the target by less than a step
    assert np.all(sent >= LOW) and np.all(sent <= HIGH)


def test_within_the_limits_the_position_asked_for_is_sent_unchanged():
    lim = RateLimiter(0.1, 0.0, LOW, HIGH)
    lim.reset(np.full(2, 0.5))
    for p in ([0.55, 0.45], [0.6, 0.5], [0.62, 0.41]):
        sent, limited = lim.limit(np.array(p))
        assert not limited and np.array_equal(sent, p)
    assert lim.limit(np.array([0.9, 0.41]))[1]  # a jump of 0.28 is limited


def test_limits_are_in_units_of_the_demonstrations_largest_step():
    demos = np.zeros((2, 11, 2))
    demos[0, :, 0] = np.linspace(0, 1, 11)  # largest step 0.1 on x
    assert largest_step(demos) == pytest.approx(0.1)
    lim = RateLimiter.from_demos(demos, 2.0, 0.5, LOW, HIGH)
    assert (lim.speed, lim.accel) == pytest.approx((0.2, 0.05))
    with pytest.raises(ValueError, match="speed > 0"):
        RateLimiter(0.0, 0.1, LOW, HIGH)


def test_the_setting_is_on_in_robot_mode_and_off_in_simulation_unless_asked():
    cfg = resolve()
    assert cfg.safety.limits("simulation") is None and cfg.safety.limits("robot") == (2.0, 0.5)
    assert resolve(overrides={"safety": {"rate_limit": "on"}}).safety.limits("simulation") == (2.0, 0.5)
    assert resolve(overrides={"safety": {"rate_limit": "off"}}).safety.limits("robot") is None
    with pytest.raises(ValueError, match="shorter than"):
        resolve(overrides={"safety": {"human_silence_s": 0.5}})


def test_kgrl_env_sends_the_limited_position_and_counts_it():
    env = KGRLEnv(load_task("passage:low_cov"), seed=0, rate_limit=(2.0, 0.5))
    free = KGRLEnv(load_task("passage:low_cov"), seed=0)
    step = 2.0 * largest_step(env.world.demos)
    env.reset(), free.reset()
    far = np.array(env.world.high)  # the human drags to a far corner
    env.set_correction(far), free.set_correction(far)
    last, limited = env.position.copy(), 0
    for _ in range(10):
        info = env.step(np.zeros(2))[4]
        info_free = free.step(np.zeros(2))[4]
        assert np.max(np.abs(info["desired"] - last)) <= step + 1e-12
        last, limited = info["desired"].copy(), limited + info["rate_limited"]
        assert info["r_a"] == pytest.approx(info_free["r_a"])  # r_a is the mapping's P_t's (eq. 7)
        assert np.array_equal(info_free["desired"], far)  # without the limit the far corner is sent at once
    assert limited == 10


def test_the_reset_path_returns_to_the_start_within_the_limits():
    env = KGRLEnv(load_task("passage:low_cov"), seed=0)
    env.reset()
    env.set_correction(np.array(env.world.high))  # the episode ends far from the start
    for _ in range(30):
        env.step(np.zeros(2))
    start = env.world.model.grid_mean[0]
    last, path = env.desired.copy(), list(env.reset_path((2.0, 0.5)))
    steps = np.abs(np.diff(np.vstack([last, *path]), axis=0))
    assert len(path) > 10 and np.max(steps) <= 2.0 * largest_step(env.world.demos) + 1e-12
    assert np.allclose(path[-1], start) and np.allclose(env.position, start, atol=1e-3)  # the robot went there


def _held_task(moved: np.ndarray | None):
    """passage:low_cov with a hold adapter that logs what it is sent and returns ``moved`` (a hand moved the robot
    there while held; None: returns nothing)."""
    from dataclasses import replace

    sent: list[np.ndarray] = []

    def hold(env, p):
        sent.append(p)
        if moved is None:
            return None
        env.robot = moved.copy()
        return moved.copy()

    return replace(load_task("passage:low_cov"), hold=hold), sent


@pytest.mark.parametrize("moved", [None, np.array([0.3, 0.6])], ids=["still", "moved-by-hand"])
def test_after_a_hold_the_limits_restart_at_rest_from_the_measured_position(moved):
    task, sent = _held_task(moved)
    env = KGRLEnv(task, seed=0, rate_limit=(2.0, 0.5))
    d = largest_step(env.world.demos)
    env.reset()
    env.set_correction(np.array(env.world.high))  # at full speed towards a far corner
    for _ in range(10):
        last = env.step(np.zeros(2))[4]["desired"]
    assert np.max(np.abs(env.limiter.velocity)) == pytest.approx(2.0 * d)
    env.hold()
    assert np.array_equal(sent[-1], last)  # the adapter gets the position last sent
    first = env.step(np.zeros(2))[4]["desired"]
    start = last if moved is None else moved  # (no measurement: from the position last sent)
    assert np.max(np.abs(first - start)) <= 0.5 * d + 1e-12  # from standstill where the robot is: one accel step


def test_the_reset_path_goes_on_from_the_last_steps_velocity_within_the_limits():
    env = KGRLEnv(load_task("passage:low_cov"), seed=0, rate_limit=(2.0, 0.5))
    d = largest_step(env.world.demos)
    env.reset()
    env.set_correction(np.array(env.world.high))
    sent = [env.desired.copy()]
    for _ in range(20):
        sent.append(env.step(np.zeros(2))[4]["desired"])
    sent += list(env.reset_path((2.0, 0.5)))  # it turns back: first it slows down
    steps = np.diff(np.array(sent), axis=0)
    assert np.max(np.abs(steps)) <= 2.0 * d + 1e-12 and np.max(np.abs(np.diff(steps, axis=0))) <= 0.5 * d + 1e-12
