"""The velocity hold shared by ``khgrl human keyboard`` and ``khgrl human gamepad`` (human_bridge/velocity.py):
which outputs a push moves (from the task descriptor), the dead zone, P_h's speed and its clipping to the
workspace box, one correction per frame while held, the keepalive, the release, the end of an episode."""

from __future__ import annotations

import numpy as np
import pytest
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import Frame
from khgrl.human_bridge.hold import KEEPALIVE_S
from khgrl.human_bridge.velocity import (
    DEAD_ZONE,
    MAX_DT,
    Push,
    VelocityHold,
    axes_of,
    axis_speeds,
    dead_zone,
    velocity,
)

FETCH_BOX = ((1.05, 0.4, 0.42), (1.55, 1.1, 0.9))  # common/tasks/fetch/task.py's workspace


def _desc(low=FETCH_BOX[0], high=FETCH_BOX[1], axes=(0, 1), third=2) -> TaskDescriptor:
    """A descriptor of O = len(low) outputs with the given workspace and views (sizes only: no real task)."""
    o, n = len(low), 5
    return TaskDescriptor(name="t", spec="t", out_dim=o, obs_dim=o, obs_low=tuple(low), obs_high=tuple(high),
                          horizon=n, workspace_low=tuple(low), workspace_high=tuple(high), G=(), c=(),
                          default_scale=(1.0,) * o, learn_scale=False, axis_names=tuple("xyzw"[:o]),
                          view_axes=axes, view_third=third, shapes=(), mean=np.zeros((n, o)),
                          demos=np.zeros((1, n, o)), projector=np.zeros((n, o, o)))


def _frame(desired, actor="a0", episode=1, t=5, last=None) -> Frame:
    p = np.asarray(desired, np.float64)
    return Frame(actor=actor, episode=episode, t=t, phase=0.5, robot=p, desired=p, mean=p, scale=np.ones_like(p),
                 intervening=False, task="t", last=last)


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


class Sink:
    def __init__(self):
        self.sent: list[tuple] = []

    def __call__(self, actor, p_h, episode, t):
        self.sent.append((actor, None if p_h is None else np.array(p_h), episode, t))

    @property
    def last(self):
        return self.sent[-1]


def _hold(task=None, speed=None):
    sink, clock = Sink(), Clock()
    return VelocityHold(task or _desc(), sink, "a0", speed, clock=clock), sink, clock


def test_pushes_move_the_descriptors_view_axes_at_a_tenth_of_the_span_per_second():
    d = _desc()
    span = np.subtract(FETCH_BOX[1], FETCH_BOX[0])
    np.testing.assert_allclose(axis_speeds(d), 0.1 * span)
    np.testing.assert_allclose(axis_speeds(d, 0.2), [0.2, 0.2, 0.2])
    s = axis_speeds(d)
    np.testing.assert_allclose(velocity(d, Push(True, h=1.0), s), [0.05, 0, 0])
    np.testing.assert_allclose(velocity(d, Push(True, v=-1.0), s), [0, -0.07, 0])
    np.testing.assert_allclose(velocity(d, Push(True, d=0.5), s), [0, 0, 0.024])
    np.testing.assert_allclose(velocity(d, Push(True, h=3.0, v=1, d=-1), s), [0.05, 0.07, -0.048])  # clipped to 1
    # the mapping comes from the descriptor, not from fixed indices
    odd = _desc(axes=(2, 0), third=1)
    assert axes_of(odd) == (2, 0, 1)
    np.testing.assert_allclose(velocity(odd, Push(True, h=1.0, v=0.5, d=-1.0), np.ones(3)), [0.5, -1.0, 1.0])
    flat = _desc((0, 0), (1, 2), third=-1)  # a 2-D task: the third push is ignored
    assert axes_of(flat) == (0, 1, None)
    np.testing.assert_allclose(velocity(flat, Push(True, h=-1, v=1, d=1), axis_speeds(flat)), [-0.1, 0.2])
    with pytest.raises(ValueError):
        axis_speeds(d, 0.0)


def test_dead_zone():
    assert DEAD_ZONE == 0.15
    assert dead_zone(0.0) == 0.0 and dead_zone(0.149) == 0.0 and dead_zone(-0.149) == 0.0
    assert dead_zone(1.0) == 1.0 and dead_zone(-1.0) == -1.0 and dead_zone(1.7) == 1.0
    assert dead_zone(0.575) == pytest.approx(0.5) and dead_zone(-0.575) == pytest.approx(-0.5)
    assert dead_zone(0.3, zone=0.5) == 0.0


def test_a_hold_starts_at_the_desired_position_moves_with_the_push_and_answers_every_frame():
    h, sink, clock = _hold()
    h.update(Push(True, h=1.0), 0.1)  # no frame yet: nowhere to start
    assert not h.holding and sink.sent == []
    h.offer(_frame([1.2, 0.7, 0.5], t=5))
    assert sink.sent == []  # a frame alone sends nothing
    h.update(Push(True, h=1.0), 0.1)  # the hold starts where the robot is told to be, sent at once
    assert h.holding and h.holds == 1
    a, p, ep, t = sink.last
    assert (a, ep, t) == ("a0", 1, 5)
    np.testing.assert_allclose(p, [1.2, 0.7, 0.5])
    for _ in range(2):  # half a second: 0.05/s, 0.07/s, 0.048/s
        h.update(Push(True, h=1.0, v=-0.5, d=1.0), 0.25)
    np.testing.assert_allclose(h.p_h, [1.2 + 0.025, 0.7 - 0.0175, 0.5 + 0.024])
    n = len(sink.sent)
    h.offer(_frame([0.0, 0.0, 0.0], t=6))  # the actor's desired position does not move a hold
    h.offer(_frame([0.0, 0.0, 0.0], actor="a1", t=99))  # another actor's frame is not answered
    h.offer(_frame([0.0, 0.0], t=98))  # nor one of another size
    assert len(sink.sent) == n + 1 and sink.last[2:] == (1, 6)
    np.testing.assert_allclose(sink.last[1], [1.225, 0.6825, 0.524])
    h.update(Push(True), 0.2)  # no push: P_h stays
    np.testing.assert_allclose(h.p_h, [1.225, 0.6825, 0.524])
    h.update(Push(True, h=-1.0), 10.0)  # a stalled loop moves P_h by at most MAX_DT's worth
    np.testing.assert_allclose(h.p_h[0], 1.225 - 0.05 * MAX_DT)


def test_p_h_is_clipped_to_the_workspace_box():
    h, sink, clock = _hold(speed=1.0)
    h.offer(_frame([2.0, 0.3, 0.5]))  # a desired position outside the box starts on its face
    h.update(Push(True), 0.0)
    np.testing.assert_allclose(sink.last[1], [1.55, 0.4, 0.5])
    for _ in range(20):
        h.update(Push(True, h=1.0, v=-1.0, d=1.0), 0.2)
        assert np.all(h.p_h >= h.low) and np.all(h.p_h <= h.high)
    np.testing.assert_allclose(h.p_h, [1.55, 0.4, 0.9])
    for _ in range(20):
        h.update(Push(True, h=-1.0, v=1.0, d=-1.0), 0.2)
    np.testing.assert_allclose(h.p_h, [1.05, 1.1, 0.42])


def test_release_on_hold_up_once_and_keepalive_while_no_frame_comes():
    h, sink, clock = _hold()
    h.offer(_frame([1.3, 0.75, 0.6], episode=2, t=40))
    h.update(Push(True), 0.0)
    n = len(sink.sent)
    clock.now += KEEPALIVE_S / 2
    h.update(Push(True, v=1.0), 0.05)
    assert len(sink.sent) == n  # sent recently
    clock.now += KEEPALIVE_S
    h.update(Push(True, v=1.0), 0.05)  # the actor is paused: no frame, but the hold stays alive
    assert len(sink.sent) == n + 1 and sink.last[1] is not None
    np.testing.assert_allclose(sink.last[1], [1.3, 0.75 + 0.007, 0.6])
    h.update(Push(False, v=1.0), 0.05)  # hold input up: one release
    assert not h.holding and sink.last == ("a0", None, 2, 40)
    n = len(sink.sent)
    h.update(Push(False), 0.05)
    clock.now += 1.0
    h.keepalive()
    h.offer(_frame([1.3, 0.75, 0.6], episode=2, t=41))
    h.release()
    assert len(sink.sent) == n  # released: nothing more
    h.update(Push(True), 0.0)  # a new hold starts at the new frame's desired position
    assert h.holds == 2 and sink.last[2:] == (2, 41)


def test_a_hold_ends_with_its_episode_and_needs_a_new_press():
    h, sink, clock = _hold()
    h.offer(_frame([1.3, 0.75, 0.6], episode=3, t=98))
    h.update(Push(True, h=1.0), 0.0)
    h.offer(_frame([1.3, 0.75, 0.6], episode=3, t=99, last=True))  # the episode's last frame: release
    assert not h.holding and h.ended and sink.last == ("a0", None, 3, 99)
    n = len(sink.sent)
    h.offer(_frame([1.2, 0.75, 0.6], episode=4, t=0))
    h.update(Push(True, h=1.0), 0.1)  # still held down: no new hold
    assert not h.holding and len(sink.sent) == n
    h.update(Push(False), 0.1)
    assert not h.ended and len(sink.sent) == n
    h.update(Push(True), 0.1)  # pressed again
    assert h.holding and sink.last[1] is not None and sink.last[2:] == (4, 0)
    # a frame of a later episode (its last frame missed) ends the hold too
    h.offer(_frame([1.2, 0.75, 0.6], episode=5, t=3))
    assert not h.holding and h.ended and sink.last[1] is None


def test_one_hold_for_every_client_with_one_keepalive():
    """The GUI's drag and the keyboard's / gamepad's hold are the same CorrectionHold (one KEEPALIVE_S)."""
    import pathlib

    import khgrl.human_bridge as hb
    from khgrl.human_bridge.gui.app import GuiApp
    from khgrl.human_bridge.hold import CorrectionHold

    assert isinstance(GuiApp(Sink(), actor="a0").hold, CorrectionHold)
    assert issubclass(VelocityHold, CorrectionHold)
    root = pathlib.Path(hb.__file__).parent
    defining = [p.relative_to(root).as_posix() for p in root.rglob("*.py") if "\nKEEPALIVE_S =" in p.read_text()]
    assert defining == ["hold.py"]


def test_the_shared_hold_answers_frames_releases_with_the_episode_and_on_a_new_actor():
    from khgrl.human_bridge.hold import CorrectionHold

    sink, clock = Sink(), Clock()
    h = CorrectionHold(sink, None, clock=clock)
    assert not h.start(np.zeros(3)) and sink.sent == []  # no actor driven yet
    h.drive("a0")
    assert h.start(np.array([1.3, 0.7, 0.6])) and sink.last[0] == "a0" and sink.last[2:] == (0, 0)
    assert not h.offer(_frame([1.0, 0.5, 0.5], episode=1, t=0))  # a hold started before any frame goes on
    assert sink.last[2:] == (1, 0) and sink.last[1] is not None
    h.offer(_frame([1.0, 0.5, 0.5], actor="a1", episode=1, t=1))  # another actor's frame: ignored
    assert len(sink.sent) == 2
    h.move(np.array([1.4, 0.7, 0.6]))
    h.keepalive()
    assert len(sink.sent) == 2  # moved, sent with the next frame or keepalive
    clock.now += 2 * KEEPALIVE_S
    h.keepalive()
    np.testing.assert_allclose(sink.last[1], [1.4, 0.7, 0.6])
    assert h.offer(_frame([1.0, 0.5, 0.5], episode=2, t=0)) is False  # started before frames: no episode end
    h.release()
    h.offer(_frame([1.0, 0.5, 0.5], episode=2, t=1))
    h.start(np.array([1.3, 0.7, 0.6]))
    assert h.offer(_frame([1.0, 0.5, 0.5], episode=3, t=0)) and not h.holding  # a later episode ends it
    h.start(np.array([1.3, 0.7, 0.6]))
    n = len(sink.sent)
    h.drive("a1")  # another actor: one release to the one held
    assert not h.holding and len(sink.sent) == n + 1 and sink.last[:2] == ("a0", None) and h.frame is None
