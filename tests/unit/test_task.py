"""The task API (khgrl.common.tasks.api, khgrl.common.tasks.world, khgrl.common.tasks.kgrl_env,
khgrl.common.wire.descriptor): a task of any O runs
through the generic KGRL environment, its descriptor survives the wire, and each kind of bad task definition
is one TaskError that names the task and what is wrong."""

from __future__ import annotations

import dataclasses
import sys
import textwrap

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from khgrl.common.tasks.api import Cuboid, Sphere, Task, TaskError, View, load_task
from khgrl.common.tasks.kgrl_env import KGRLEnv
from khgrl.common.tasks.world import build_task_world
from khgrl.common.wire.descriptor import TaskDescriptor
from khgrl.common.wire.messages import TaskInfo
from khgrl.common.wire.protocol import ProtocolError, decode, encode
from khgrl.deploy.examples.own_task import make_task as own_task


def _task(**over) -> Task:
    return dataclasses.replace(own_task(), **over)


@pytest.fixture(scope="module")
def own_env() -> KGRLEnv:
    return KGRLEnv(own_task(), seed=3)


def test_the_example_task_is_a_clean_gymnasium_env(own_env) -> None:
    check_env(own_env, skip_render_check=True)
    check_env(own_task().make_env(0), skip_render_check=True)
    assert own_env.action_space.shape == (3,)
    assert own_env.observation_space.shape == (3 + 1 + 3,)  # env observation, phase, deviation


def test_the_example_task_steps_with_o_3(own_env) -> None:
    obs, _ = own_env.reset(seed=1)
    assert obs.shape == (7,) and obs[3] == 0.0
    total, steps = 0.0, 0
    done = False
    while not done:
        obs, r, term, trunc, info = own_env.step(own_env.action_space.sample())
        total += r
        steps += 1
        done = term or trunc
        assert info["desired"].shape == (3,) and info["action"].shape == (3,)
        assert np.all(info["desired"] >= own_env.world.low - 1e-9) and np.all(info["desired"] <= own_env.world.high
                                                                                + 1e-9)
    assert steps <= own_env.horizon and np.isfinite(total)


def test_a_correction_in_3d_is_eq_6_with_projection(own_env) -> None:
    own_env.reset(seed=0)
    own_env.set_correction(np.array([0.3, 0.5, 5.0]))  # z far above the workspace: projected onto it
    _, _, _, _, info = own_env.step(np.zeros(3))
    assert info["intervened"] and info["projected"]
    assert info["desired"][2] == pytest.approx(own_env.world.high[2])
    with pytest.raises(ValueError, match="finite \\(3,\\)"):
        own_env.set_correction(np.array([0.3, 0.5]))


def test_descriptor_round_trip_and_digest(own_env) -> None:
    d = own_env.descriptor("khgrl.deploy.examples.own_task:make_task")
    assert (d.out_dim, d.obs_dim, d.horizon, d.third) == (3, 7, 200, 2)
    back = decode(TaskInfo, encode(TaskInfo(sender_id="a0", descriptor=d), "a0", 0)).descriptor
    assert back.digest == d.digest and np.array_equal(back.mean, d.mean) and back.shapes[0]["kind"] == "box"
    other = KGRLEnv(_task(default_scale=6.0)).descriptor("khgrl.deploy.examples.own_task:make_task")
    assert other.digest != d.digest  # another L0 is another task


def test_a_bad_descriptor_is_refused() -> None:
    d = KGRLEnv(own_task()).descriptor("x:y").to_wire()
    for field, value, reason in [("out_dim", 0, "out_dim"), ("view_axes", [0, 7], "view_axes"),
                                 ("c", [0.0], "c"), ("shapes", [{"kind": "cone", "name": "x"}], "cone")]:
        with pytest.raises(ProtocolError, match=reason):
            TaskDescriptor.from_wire({**d, field: value})


# ------------------------------------------------------------------------------------ bad task definitions
BAD = [
    (dict(demos=np.zeros((4, 50))), "shape \\(M demos, N steps, O outputs\\)"),
    (dict(demos=np.full((4, 50, 3), np.nan)), "non-finite"),
    (dict(workspace=((0, 0), (1, 1))), "workspace low needs 3 values"),
    (dict(workspace=((0, 0, 0), (1, 0, 1))), "low < high"),
    (dict(constraints=(np.array([[0.0, 0.0, 1.0]]), np.array([0.7]))), "violates hard constraint 6, your constraint 0"),
    (dict(scripted_human=lambda mean: mean[:2]), "scripted_human must return None or 3 finite values"),
    (dict(scripted_human=lambda mean: 1 / 0), "scripted_human raised ZeroDivisionError"),
    (dict(constraints=(np.array([[0.0, 0.0, 1.0]]), np.array([0.9]))), "admit no point"),  # z >= 0.9 > 0.8
    (dict(constraints=(np.zeros((1, 2)), np.zeros(1))), "constraints need G of shape \\(K, 3\\)"),
    (dict(default_scale=(1.0, 2.0)), "default_scale needs 3 values"),
    (dict(default_scale=-1.0), "default_scale must be > 0"),
    (dict(view=View(axes=(0, 5))), "view axes"),
    (dict(view=View(shapes=(Sphere("ball", (0.5, 0.5), 0.1),))), "shape 'ball' center needs 3 values"),
    (dict(view=View(shapes=(Cuboid("b", (0, 0, 0), (1, 1, np.inf)),))), "not finite"),
]


@pytest.mark.parametrize("over,reason", BAD, ids=[r for _, r in BAD])
def test_bad_task_definitions_are_one_clear_error(over: dict, reason: str) -> None:
    with pytest.raises(TaskError, match=reason) as info:
        build_task_world(_task(**over))
    assert "point-3d" in str(info.value)  # names the task


def test_an_env_whose_action_is_not_the_command_is_refused() -> None:
    bad = _task(make_env=lambda seed: gym.make("CartPole-v1"))
    with pytest.raises(TaskError, match="observation space|action must be the desired position"):
        KGRLEnv(bad)

    def boom(seed):
        raise RuntimeError("robot not found on /dev/ttyUSB0")

    with pytest.raises(TaskError, match="make_env raised RuntimeError: robot not found"):
        KGRLEnv(_task(make_env=boom))


def test_load_task_specs(tmp_path, monkeypatch) -> None:
    assert load_task("passage:low_cov").name == "passage-low_cov"
    assert load_task("khgrl.deploy.examples.own_task:make_task").name == "point-3d"
    for spec, reason in [("nonsense", "expected"), ("no_such_module_x:make", "cannot import"),
                         ("khgrl.deploy.examples.own_task:nothing", "no callable"),
                         ("passage:mars", "unknown scenario")]:
        with pytest.raises(TaskError, match=reason):
            load_task(spec)
    # a module in the current directory is found without PYTHONPATH; a factory that raises is named
    (tmp_path / "my_tasks_mod.py").write_text(textwrap.dedent("""
        from khgrl.deploy.examples.own_task import make_task
        def broken():
            raise KeyError("gripper")
        def wrong():
            return 42
    """))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    assert load_task("my_tasks_mod:make_task").name == "point-3d"
    with pytest.raises(TaskError, match="factory raised KeyError"):
        load_task("my_tasks_mod:broken")
    with pytest.raises(TaskError, match="returned int"):
        load_task("my_tasks_mod:wrong")


def test_demos_file_replaces_the_task_demos(tmp_path) -> None:
    from khgrl.common.tasks.demos import save_demos

    demos = own_task().demos[:3, ::2]  # 3 demos of 100 steps
    path = save_demos(tmp_path / "d.npz", demos)
    env = KGRLEnv(load_task("khgrl.deploy.examples.own_task:make_task", demos=path))
    assert env.horizon == 100 and env.world.demos.shape == (3, 100, 3)
