"""Delta control (``--method hil-serl``, :mod:`khgrl.common.tasks.delta`) in :class:`KGRLEnv`, the passage world's
takeover human, the safety counts of ``episodes.csv`` and how the experiment runs the new methods."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from khgrl.common.config.settings import resolve
from khgrl.common.metrics import EpisodeAccumulator
from khgrl.common.tasks.api import load_task
from khgrl.common.tasks.delta import STEP_FACTOR, DeltaControl
from khgrl.common.tasks.kgrl_env import KGRLEnv

OWN = "khgrl.deploy.examples.own_task:make_task"


def test_step_size_is_twice_the_largest_demonstrated_step():
    demos = np.zeros((2, 4, 2))
    demos[0, :, 0] = [0.0, 0.1, 0.15, 0.2]
    demos[1, :, 1] = [0.0, -0.05, -0.3, -0.3]  # the largest: 0.25 on y
    dc = DeltaControl.from_demos(demos, np.zeros(2) - 1, np.ones(2))
    assert dc.step == pytest.approx(STEP_FACTOR * 0.25)
    with pytest.raises(ValueError, match="do not move"):
        DeltaControl.from_demos(np.zeros((1, 3, 2)), -np.ones(2), np.ones(2))


def test_act_clips_to_the_box_and_invert_reaches_the_target():
    dc = DeltaControl(0.1, np.zeros(2), np.ones(2))
    p, exited = dc.act(np.array([0.95, 0.5]), np.array([1.0, -1.0]))
    assert exited and np.allclose(p, [1.0, 0.4])
    p, exited = dc.act(np.array([0.5, 0.5]), np.array([0.5, 0.0]))
    assert not exited and np.allclose(p, [0.55, 0.5])
    a, clipped = dc.invert(np.array([0.5, 0.5]), np.array([0.53, 0.9]))
    assert clipped and np.allclose(a, [0.3, 1.0])
    a, clipped = dc.invert(np.array([0.5, 0.5]), np.array([0.45, 0.52]))
    assert not clipped and np.allclose(dc.act(np.array([0.5, 0.5]), a)[0], [0.45, 0.52])


def test_delta_env_moves_from_the_position_and_stores_the_takeover_action():
    env = KGRLEnv(load_task(OWN), seed=1, control="delta")
    obs, _ = env.reset(seed=1)
    start = env.position.copy()
    _, r, _, _, info = env.step(np.ones(3, dtype=np.float32))
    want = np.clip(start + env.delta.step, env.world.low, env.world.high)
    assert np.allclose(info["desired"], want) and info["r_a"] == 0.0 and not info["intervened"]
    assert np.allclose(info["xi"], 0.0)
    p_h = env.position + np.array([0.3, -0.3 * env.delta.step, 0.0])  # far on x (clipped), near on y
    env.set_correction(p_h)
    pos = env.position.copy()
    _, _, _, _, info = env.step(np.zeros(3, dtype=np.float32))
    a_h = np.clip((np.clip(p_h, env.world.low, env.world.high) - pos) / env.delta.step, -1, 1)
    assert info["intervened"] and info["clipped"] and np.allclose(info["action"], a_h, atol=1e-6)
    assert np.allclose(info["desired"], np.clip(pos + env.delta.step * a_h, env.world.low, env.world.high))


@pytest.mark.parametrize("spec", [OWN, "fetch:moved"])
def test_kmp_env_counts_no_violation_and_no_exit_for_the_policy(spec):
    env = KGRLEnv(load_task(spec), seed=1)
    env.reset(seed=1)
    acc = EpisodeAccumulator()
    acc.start()
    rng = np.random.default_rng(0)
    on_box = 0
    for _ in range(60):  # full-scale actions: the QP holds P_t on the box's faces (to its rounding)
        _, r, _, _, info = env.step(rng.choice([-1.0, 1.0], 3).astype(np.float32))
        acc.add(r, info)
        on_box += bool(np.any(np.isclose(info["desired"], env.world.low) | np.isclose(info["desired"], env.world.high)))
    st = acc.finish()
    assert st.violation_steps == 0 and st.workspace_exits == 0 and st.human_seconds == 0.0, on_box


def test_delta_env_counts_workspace_exits():
    env = KGRLEnv(load_task("passage:low_cov"), seed=1, control="delta")
    env.reset(seed=1)
    acc = EpisodeAccumulator()
    acc.start()
    for _ in range(120):  # down and left, into the box's corner and on against it
        _, r, term, trunc, info = env.step(np.array([-1.0, -1.0], dtype=np.float32))
        acc.add(r, info)
        if term or trunc:
            break
    assert acc.finish().workspace_exits >= 1


def test_passage_takeover_steers_from_the_robot_in_the_same_steps():
    task = load_task("passage:low_cov")
    guide = task.scripted_human
    takeover = guide.takeover
    inside = np.array([np.mean(guide.window), 0.5])
    outside = np.array([guide.window[0] - 0.05, 0.5])
    assert takeover(outside, np.array([0.1, 0.1])) is None  # helps when the guide does, by the mean
    x = inside[0]
    off = np.array([x - 0.1, guide.path_y(x - 0.1) + 0.2])  # the robot below/above the path: straight onto it
    assert np.allclose(takeover(inside, off), [off[0], guide.path_y(off[0])])
    on = np.array([x - 0.1, guide.path_y(x - 0.1)])  # on the path: along it
    ahead = on[0] + takeover.LOOKAHEAD
    assert np.allclose(takeover(inside, on), [ahead, guide.path_y(ahead)])


def test_hil_serl_implies_its_recipe_unless_set():
    cfg = resolve(overrides={"method": "hil-serl"})
    assert (cfg.algo, cfg.tqc.sampling) == ("sac_ln", "rlpd")
    cfg = resolve(overrides={"method": "hil-serl", "algo": "tqc", "tqc": {"sampling": "uniform"}})
    assert (cfg.algo, cfg.tqc.sampling) == ("tqc", "uniform")
    cfg = resolve(overrides={"method": "khgrl"})
    assert (cfg.algo, cfg.tqc.sampling) == ("tqc", "uniform")


def test_experiment_runs_the_new_methods_with_their_flags():
    from khgrl.deploy.experiments.experiment import load_config, plan_runs, run_argv
    from khgrl.deploy.experiments.run_results import RUN_NAME

    cfg = load_config(None, {"tasks": ["fetch:moved"], "methods": ["khgrl_rlpd", "hil-serl"], "seeds": [0]})
    argv = {s.method: run_argv(s, cfg, Path("x")) for s in plan_runs(cfg)}
    rlpd, hil = argv["khgrl_rlpd"], argv["hil-serl"]
    assert rlpd[rlpd.index("--method") + 1] == "khgrl" and rlpd[rlpd.index("--sampling") + 1] == "rlpd"
    assert hil[hil.index("--method") + 1] == "hil-serl" and hil[hil.index("--human") + 1] == "scripted"
    for name in ("fetch_moved-hil-serl-seed3", "passage_low_cov-khgrl_rlpd-seed0"):
        assert RUN_NAME.match(name)
