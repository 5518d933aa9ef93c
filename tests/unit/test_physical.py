"""Physical corrections: the detector (common/tasks/physical.py) and the detection measure (actor/physical.py)."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.actor.physical import PhysicalHands, detection
from khgrl.common.tasks.physical import PhysicalDetector


def _feed(det: PhysicalDetector, sent: list, measured: list) -> list[bool]:
    return [det.update(np.array(p), np.array(b), np.array(a)) for p, b, a in zip(sent, measured, measured[1:])]


def test_a_held_deviation_starts_an_interaction_and_stillness_ends_it():
    det = PhysicalDetector(deviation=0.03, motion=0.005, on_steps=2, off_steps=3)
    sent = [[0.0, 0.0]] * 10
    arm = [[0, 0], [0.01, 0], [0.04, 0], [0.05, 0], [0.08, 0], [0.10, 0], [0.101, 0], [0.101, 0], [0.101, 0],
           [0.101, 0], [0.101, 0]]
    held = [False, False, True, True, True, True, True, False, False, True]  # (still held off: a hand again)
    assert _feed(det, sent, arm) == held


def test_tracking_lag_and_a_single_jump_are_not_a_hand():
    det = PhysicalDetector(deviation=0.03, motion=0.005)
    sent = [[0.1 * (k + 1), 0.0] for k in range(10)]  # each step's command, reached at its end
    arm = [[0.1 * k - 0.02, 0.0] for k in range(11)]  # 2 cm behind a moving command
    assert not any(_feed(det, sent, arm))
    det.reset()
    assert not any(_feed(det, [[0.0, 0.0]] * 3, [[0, 0], [0.05, 0], [0.0, 0], [0.0, 0]]))  # one step off


def test_thresholds_are_in_units_of_the_demonstrations_step():
    demos = np.zeros((2, 5, 2))
    demos[0, :, 1] = np.arange(5) * 0.02
    det = PhysicalDetector.from_demos(demos)
    assert (det.deviation, det.motion) == pytest.approx((0.024, 0.005))


def test_detection_counts_steps_delays_and_quiet_episodes():
    rows = [{"episode": e, "step": t, "pushed": int(p), "detected": int(d)} for e, t, p, d in [
        (1, 0, 0, 0), (1, 1, 0, 1), (1, 2, 0, 0),  # a false detection in a quiet episode
        (2, 0, 1, 0), (2, 1, 1, 0), (2, 2, 1, 1), (2, 3, 0, 1), (2, 4, 0, 0)]]
    d = detection(rows)
    assert (d["pushed"], d["detected"], d["delay_steps"]) == (3, 3, [2])
    assert d["precision"] == pytest.approx(1 / 3) and d["recall"] == pytest.approx(1 / 3)
    assert (d["false_in_quiet_episodes"], d["quiet_episodes"]) == (1, 1)


def test_off_does_nothing_and_a_task_without_a_push_hook_is_refused():
    off = PhysicalHands.off()
    p_h = np.ones(2)
    assert off.correction(3, p_h) == (p_h, False) and off.counts["detected_steps"] == 0
    from khgrl.common.tasks.api import TaskError, load_task
    from khgrl.common.tasks.kgrl_env import KGRLEnv

    with pytest.raises(TaskError, match="no push hook"):
        PhysicalHands(KGRLEnv(load_task("passage:low_cov")), "scripted")


def test_no_interaction_starts_while_the_task_says_the_robot_is_in_contact():
    det = PhysicalDetector(deviation=0.03, motion=0.005, on_steps=2, off_steps=3)
    arm = [[0, 0], [0.05, 0], [0.06, 0], [0.07, 0], [0.08, 0]]
    held = [det.update(np.zeros(2), np.array(b), np.array(a), contact=c)
            for (b, a), c in zip(zip(arm, arm[1:]), (True, True, False, False))]
    assert held == [False, False, False, True]  # the count starts only once the contact is over
